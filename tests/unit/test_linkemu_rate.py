"""The link emulator's schedule under a rate cap: the wire carries one frame after another."""

from __future__ import annotations

import random

import pytest

from cli.scenario.linkemu import QUEUE_LIMIT, Direction, Impairment


def _direction(**impairment) -> Direction:
    imp = Impairment()
    imp.set(**impairment)
    return Direction("a->b", None, None, imp, random.Random(0))  # type: ignore[arg-type]  # no sockets needed


def test_frames_leave_one_wire_time_after_another_then_their_delay():
    d = _direction(rate_mbit=8.0, delay_ms=10)  # 8 Mbit/s: a 1000-byte frame takes 1 ms on the wire
    times = [d.schedule(100.0, 1000, waiting=i) for i in range(3)]
    assert times == pytest.approx([100.011, 100.012, 100.013])
    later = d.schedule(101.0, 500, waiting=0)  # the wire was idle meanwhile: no backlog carried over
    assert later == pytest.approx(101.0 + 0.0005 + 0.010)


def test_a_full_queue_drops_and_no_cap_means_delay_only():
    d = _direction(rate_mbit=1.0)
    assert d.schedule(0.0, 1500, waiting=QUEUE_LIMIT) is None
    free = _direction(delay_ms=5)
    assert free.schedule(1.0, 10**6, waiting=10**6) == pytest.approx(1.005)  # no cap: size and queue do not matter


def test_a_negative_rate_is_refused():
    with pytest.raises(ValueError, match="rate_mbit"):
        Impairment().set(rate_mbit=-1)
