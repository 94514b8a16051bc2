"""A bag replayed at its recorded pace: items wait for their time, a rate of 0 does not wait, a stop ends it."""

import threading
import time

from protocol.pacing import paced

STAMPED = [(1_000_000_000, "a"), (1_060_000_000, "b"), (1_120_000_000, "c")]  # 60 ms apart


def test_items_come_in_order_at_rate_times_their_recorded_pace():
    t0 = time.monotonic()
    arrivals = [(item, time.monotonic() - t0) for item in paced(STAMPED, rate=2.0)]
    assert [a for a, _ in arrivals] == ["a", "b", "c"]
    assert arrivals[1][1] >= 0.03 and arrivals[2][1] >= 0.06  # twice the recorded pace: 30 ms apart
    assert list(paced(STAMPED, rate=0)) == ["a", "b", "c"]


def test_a_stop_ends_the_replay_while_it_waits():
    stop = threading.Event()
    far = [(0, "now"), (3_600_000_000_000, "in an hour")]
    threading.Timer(0.05, stop.set).start()
    t0 = time.monotonic()
    assert list(paced(far, rate=1.0, stop=stop)) == ["now"]
    assert time.monotonic() - t0 < 5
    assert list(paced(STAMPED, rate=1.0, stop=stop)) == []  # already stopped: nothing
