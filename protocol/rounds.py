"""Per-round mailbox and the round barrier with a deadline.

Zenoh callbacks :meth:`Mailbox.offer` what arrives (decoded snapshots, or raw bytes to decode
later); the daemon's round loop calls :meth:`Mailbox.wait` for the current round and then
:meth:`Mailbox.advance`::

    box = Mailbox(max_ahead=4)
    box.offer(sender=2, round=7, item=snapshot)          # from a Zenoh thread
    got = box.wait(7, expected=lambda: membership.live_neighbours, timeout_s=30.0)
    got.items        # {sender: item} for round 7
    got.waited_s     # seconds spent waiting (network time of the round)
    box.advance(8)   # round 7 and older are dropped; 8 .. 8+max_ahead stay buffered

Rules:

- a round older than the current round is ``stale_round`` and refused;
- rounds up to ``max_ahead`` past the current one are buffered, so a fast neighbour's next
  snapshot is not lost (bounded memory: at most ``max_ahead + 1`` rounds per sender);
- a round further ahead is not buffered for its round but kept as that sender's newest (one
  item per sender): a robot that fell far behind (frozen, cut off) learns where its neighbours
  are, can jump there, and finds the item in place on :meth:`advance` to that round;
- a round past ``last_round`` (the swarm's last round, when given) is ``too_far_ahead`` and refused;
- the same (sender, round) offered again is ignored: the **first** valid copy is kept, so that
  no later message can swap a snapshot already taken in (a replay, a forgery);
- :meth:`newest_round` can be asked for the newest round *up to* a bound, so that a snapshot
  from the far future, which no one can vouch for, never decides anything by itself.

``expected()`` is re-evaluated on every wake-up, since neighbours may die during the wait;
:meth:`notify` wakes waiters when membership changes. ``expected`` is called without the
mailbox lock held, so it may take other locks (no lock-order deadlock with membership).

Thread-safe; pure Python.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Generic, Iterable, TypeVar

from protocol.messages import Rejected

T = TypeVar("T")


@dataclass
class WaitResult(Generic[T]):
    """What :meth:`Mailbox.wait` collected, and how long it took."""

    round: int
    items: dict[int, T]
    waited_s: float
    complete: bool  # every expected sender delivered before the deadline
    missing: frozenset[int] = field(default_factory=frozenset)  # expected at return time, not delivered


class Mailbox(Generic[T]):
    """Items keyed by (sender, round), with a barrier on one round."""

    def __init__(self, max_ahead: int, current_round: int = 0, poll_s: float = 0.5, last_round: int | None = None):
        if type(max_ahead) is not int or max_ahead < 0:
            raise ValueError("max_ahead must be a non-negative int")
        if type(current_round) is not int or current_round < 0:
            raise ValueError("current_round must be a non-negative int")
        self.max_ahead = max_ahead
        self.last_round = last_round
        self._current = current_round
        self._poll_s = poll_s  # safety net if someone forgets notify() on membership changes
        self._items: dict[int, dict[int, T]] = {}  # round -> sender -> item
        self._newest: dict[int, tuple[int, T]] = {}  # sender -> (round, item), survives advance()
        self._generation = 0  # bumped by notify(): tells a waiter to re-read expected()
        self._cond = threading.Condition()

    @property
    def current_round(self) -> int:
        with self._cond:
            return self._current

    def offer(self, sender: int, round: int, item: T) -> None:
        """Store an item for (sender, round). Raises Rejected('stale_round'|'too_far_ahead')."""
        with self._cond:
            if round < self._current:
                raise Rejected("stale_round", f"round {round} from {sender}, current round {self._current}")
            if self.last_round is not None and round > self.last_round:
                raise Rejected("too_far_ahead", f"round {round} from {sender}, the last round is {self.last_round}")
            if round <= self._current + self.max_ahead:
                self._items.setdefault(round, {}).setdefault(sender, item)
            newest = self._newest.get(sender)
            if newest is None or round > newest[0]:
                self._newest[sender] = (round, item)
            self._cond.notify_all()

    def notify(self) -> None:
        """Wake waiters so they re-evaluate ``expected()`` (call on every membership change)."""
        with self._cond:
            self._generation += 1
            self._cond.notify_all()

    def wait(self, round: int, expected: Callable[[], Iterable[int]], timeout_s: float) -> WaitResult[T]:
        """Block until every id in ``expected()`` has an item for ``round``, or ``timeout_s`` passes.

        Returns what arrived for that round (possibly from senders no longer expected, which
        the caller may still use or ignore).
        """
        start = time.monotonic()
        deadline = start + max(0.0, timeout_s)
        while True:
            with self._cond:
                generation = self._generation
            wanted = frozenset(expected())  # outside the lock: may take other locks
            with self._cond:
                got = self._items.get(round, {})
                missing = wanted - got.keys()
                now = time.monotonic()
                if not missing or now >= deadline:
                    return WaitResult(round, dict(got), now - start, not missing, frozenset(missing))
                if self._generation == generation:  # else membership changed meanwhile: re-read now
                    self._cond.wait(min(deadline - now, self._poll_s))

    def advance(self, round: int) -> None:
        """Make ``round`` current; drop every item of older rounds."""
        with self._cond:
            if round < self._current:
                raise ValueError(f"cannot go back from round {self._current} to {round}")
            self._current = round
            for r in [r for r in self._items if r < round]:
                del self._items[r]
            for sender, (r, item) in self._newest.items():  # kept while it was too far ahead
                if round <= r <= round + self.max_ahead:
                    self._items.setdefault(r, {}).setdefault(sender, item)
            self._cond.notify_all()

    def items(self, round: int) -> dict[int, T]:
        """What is held for ``round`` now, without waiting."""
        with self._cond:
            return dict(self._items.get(round, {}))

    def newest_round(self, sender: int, at_most: int | None = None) -> int | None:
        """Newest round offered by ``sender`` (accepted offers only), or None; with ``at_most``, the
        newest of the rounds held that are not beyond it."""
        found = self.newest_item(sender, at_most)
        return None if found is None else found[0]

    def newest_item(self, sender: int, at_most: int | None = None) -> tuple[int, T] | None:
        """(round, item) of :meth:`newest_round`."""
        with self._cond:
            held = [(r, per[sender]) for r, per in self._items.items() if sender in per]
            if sender in self._newest:
                held.append(self._newest[sender])
            held = [h for h in held if at_most is None or h[0] <= at_most]
            return max(held, key=lambda h: h[0], default=None)

    def newest_items(self) -> dict[int, tuple[int, T]]:
        """sender -> (round, item) of the newest accepted offer: for catching up after a restart."""
        with self._cond:
            return dict(self._newest)

    def forget(self, sender: int) -> None:
        """Drop everything from one sender (e.g. it left the swarm)."""
        with self._cond:
            self._newest.pop(sender, None)
            for per_round in self._items.values():
                per_round.pop(sender, None)
