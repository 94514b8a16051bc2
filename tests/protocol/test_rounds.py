"""Mailbox / round barrier semantics, with real threads."""

import threading
import time

import pytest

from protocol.messages import Rejected
from protocol.rounds import Mailbox


def later(delay, fn, *args):
    t = threading.Timer(delay, fn, args)
    t.start()
    return t


def test_returns_as_soon_as_all_expected_arrived():
    box = Mailbox(max_ahead=2)
    later(0.05, box.offer, 1, 0, "a")
    later(0.10, box.offer, 2, 0, "b")
    got = box.wait(0, lambda: {1, 2}, timeout_s=5.0)
    assert got.items == {1: "a", 2: "b"} and got.complete and not got.missing
    assert 0.08 <= got.waited_s < 1.0


def test_deadline_returns_what_arrived():
    box = Mailbox(max_ahead=2)
    box.offer(1, 0, "a")
    t0 = time.monotonic()
    got = box.wait(0, lambda: {1, 2}, timeout_s=0.2)
    assert 0.18 <= time.monotonic() - t0 < 1.0
    assert got.items == {1: "a"} and not got.complete and got.missing == {2}
    assert got.waited_s >= 0.18


def test_expected_set_shrinking_during_the_wait_releases_the_barrier():
    box = Mailbox(max_ahead=2, poll_s=10.0)  # no polling: only notify() can wake the waiter
    alive = {1, 2}
    box.offer(1, 0, "a")

    def neighbour_2_dies():
        alive.discard(2)
        box.notify()

    later(0.1, neighbour_2_dies)
    got = box.wait(0, lambda: set(alive), timeout_s=5.0)
    assert got.complete and got.items == {1: "a"}
    assert got.waited_s < 1.0


def test_no_expected_neighbours_returns_at_once():
    box = Mailbox(max_ahead=1)
    got = box.wait(3, lambda: set(), timeout_s=5.0)
    assert got.complete and got.items == {} and got.waited_s < 0.1


def test_future_rounds_are_buffered_and_stale_ones_refused():
    box = Mailbox(max_ahead=2, last_round=10)
    box.offer(1, 1, "r1")
    box.offer(1, 2, "r2")
    with pytest.raises(Rejected) as exc:
        box.offer(1, 11, "past the end")
    assert exc.value.reason == "too_far_ahead"
    assert box.wait(0, lambda: {1}, timeout_s=0.05).items == {}
    box.advance(1)
    assert box.wait(1, lambda: {1}, timeout_s=1.0).items == {1: "r1"}
    box.advance(2)
    assert box.items(2) == {1: "r2"}
    with pytest.raises(Rejected) as exc:
        box.offer(1, 1, "late")
    assert exc.value.reason == "stale_round"
    box.offer(1, 4, "r4")  # now within max_ahead
    assert box.items(1) == {}  # dropped by advance


def test_a_round_beyond_the_window_is_kept_as_the_newest_only():
    """A robot that froze for a while must learn how far ahead its neighbours are, and jump there."""
    box = Mailbox(max_ahead=2)
    box.offer(1, 9, "r9")  # 9 > 0 + 2: not buffered for round 9 ...
    box.offer(2, 7, "b7")
    box.offer(2, 8, "b8")  # only the newest per sender is kept
    assert box.items(9) == {} and box.items(7) == {}
    assert box.newest_round(1) == 9 and box.newest_items() == {1: (9, "r9"), 2: (8, "b8")}
    box.advance(7)  # ... and in place once 9 is within the window
    assert box.items(9) == {1: "r9"} and box.items(8) == {2: "b8"} and box.items(7) == {}
    assert box.wait(9, lambda: {1}, timeout_s=0.05).complete


def test_the_first_copy_of_a_round_is_kept():
    """A replay or a forgery of a (sender, round) already taken in changes nothing."""
    box = Mailbox(max_ahead=1)
    box.offer(1, 0, "first")
    box.offer(1, 0, "second")
    assert box.items(0) == {1: "first"}
    box.offer(1, 5, "far")
    box.offer(1, 5, "far again")
    assert box.newest_items() == {1: (5, "far")}


def test_the_newest_round_up_to_a_bound_ignores_the_far_future():
    box = Mailbox(max_ahead=2)
    box.offer(1, 1, "r1")
    box.offer(1, 90, "forged")  # beyond the window: kept as newest only
    assert box.newest_round(1) == 90
    assert box.newest_round(1, at_most=3) == 1 and box.newest_item(1, at_most=3) == (1, "r1")
    assert box.newest_round(1, at_most=0) is None and box.newest_round(2, at_most=5) is None


def test_newest_round_and_items_for_catching_up():
    box = Mailbox(max_ahead=10)
    assert box.newest_round(1) is None
    box.offer(1, 3, "a3")
    box.offer(1, 2, "a2")  # older than newest: buffered but not newest
    box.offer(2, 5, "b5")
    assert box.newest_round(1) == 3 and box.newest_round(2) == 5
    box.advance(6)  # newest info survives advance, for a restarted robot to jump ahead
    assert box.newest_items() == {1: (3, "a3"), 2: (5, "b5")}
    box.forget(2)
    assert box.newest_round(2) is None


def test_advance_cannot_go_back_and_args_are_checked():
    box = Mailbox(max_ahead=1, current_round=5)
    with pytest.raises(ValueError):
        box.advance(4)
    with pytest.raises(ValueError):
        Mailbox(max_ahead=-1)


def test_many_threads_offering_while_waiting():
    box = Mailbox(max_ahead=3)
    senders = list(range(1, 9))

    def send(i):
        for r in range(4):
            time.sleep(0.001 * i)
            box.offer(i, r, (i, r))

    threads = [threading.Thread(target=send, args=(i,)) for i in senders]
    for t in threads:
        t.start()
    for r in range(4):
        got = box.wait(r, lambda: set(senders), timeout_s=5.0)
        assert got.complete and got.items == {i: (i, r) for i in senders}
        box.advance(r + 1)
    for t in threads:
        t.join()
