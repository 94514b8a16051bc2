"""How much of what neighbours say a robot believes about rounds: no single neighbour moves it.

A robot's round moves forward by training, or by a join or catch-up when its neighbours are
ahead. The evidence for "ahead" is what neighbours say of themselves, so one neighbour that lies
(captured, crashed into a bad state, running buggy code) must not be able to decide it:

- :class:`ClaimPace`: a neighbour's claimed round counts only as far as its pace explains. Each
  neighbour earns one round of credit per ``min_round_s`` of our clock (the fastest a round can
  run here, from our own measured rounds), holds at most ``burst`` rounds of credit while it
  keeps talking, and spends one per round it claims to advance past one beyond ours. A silence
  earns credit for the whole silence (a neighbour we could not hear may well have trained
  meanwhile). A claim past its credit is cut to what the credit explains, and the neighbour is
  flagged.
- :func:`quorum_round`: the round a strict majority of the neighbours has reached (the k-th
  largest, k = n // 2 + 1), never the maximum.
- :func:`plan_catch_up`: train through a short gap or skip a long one, to the quorum's round.
- :class:`RefusalStreaks`: a neighbour whose snapshots are refused round after round (NaN, a
  broken encoder) stops holding the barrier.

Pure Python, thread-safe where it says so, no clocks of its own: times are passed in.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Iterable, Literal, Mapping

__all__ = ["ClaimPace", "quorum_round", "plan_catch_up", "RefusalStreaks"]


@dataclass
class _Credit:
    round: int  # the newest round of the neighbour's that its pace explains
    claim: int  # what it claims, believed or not
    at: float  # when we last heard its claim
    credit: float  # rounds it may still advance without waiting


class ClaimPace:
    """Per neighbour, its claimed round bounded by its pace (see the module docstring). Thread-safe."""

    def __init__(self, burst: float = 2.0) -> None:
        if burst < 1:
            raise ValueError("burst must be >= 1 round")
        self.burst = burst
        self.min_round_s: float | None = None  # None: no round measured yet, every claim counts
        self._lock = threading.Lock()
        self._peers: dict[int, _Credit] = {}

    def observe(self, j: int, claim: int, now: float, own_round: int) -> bool:
        """j says it has completed round ``claim`` (heard at ``now``; we are at ``own_round``).
        True when the claim runs ahead of what j's pace explains (and was cut to it).

        A claim up to one past our own round is believed as it is: no such claim can move us,
        and a neighbour that skipped to our round after a freeze is no liar. Beyond that, a
        first claim is believed up to there, and the rest must be earned by pace; without a
        measured round of ours (``min_round_s`` None) nothing more is believed. (Joining at
        start does not pace: it takes the quorum of the raw claims.)"""
        floor = own_round + 1
        with self._lock:
            peer = self._peers.get(j)
            if peer is None:
                self._peers[j] = _Credit(min(claim, floor), claim, now, self.burst)
                return claim > floor
            if claim <= max(floor, peer.round):  # harmless, or not ahead of what we believe
                peer.round, peer.claim, peer.at = claim, claim, now
                peer.credit = min(peer.credit, self.burst)
                return False
            peer.round = max(peer.round, floor)
            if self.min_round_s is None:
                peer.claim, peer.at = claim, now
                return True
            peer.credit = min(peer.credit, self.burst) + max(now - peer.at, 0.0) / self.min_round_s
            step = min(claim - peer.round, math.floor(peer.credit))
            peer.round += step
            peer.credit -= step
            peer.claim, peer.at = claim, now
            return peer.round < claim

    def credible(self, j: int) -> int | None:
        """j's claimed round as far as its pace explains it; None before its first claim."""
        with self._lock:
            peer = self._peers.get(j)
            return None if peer is None else peer.round

    def ahead_of_pace(self) -> dict[int, tuple[int, int]]:
        """The neighbours whose claim runs ahead of their pace: j -> (claimed, believed)."""
        with self._lock:
            return {j: (p.claim, p.round) for j, p in self._peers.items() if p.claim > p.round}


def quorum_round(rounds: Iterable[int]) -> int | None:
    """The newest round that a strict majority of these neighbours has reached: the k-th largest,
    k = n // 2 + 1 (with two neighbours, the lower; with one, its own). None without any."""
    ordered = sorted(rounds, reverse=True)
    return ordered[len(ordered) // 2] if ordered else None


def plan_catch_up(round_index: int, newest: Mapping[int, int | None], round_compute_s: float | None,
                  max_neighbour_wait_s: float, last_round: int | None = None
                  ) -> tuple[Literal["train", "skip"], int] | None:
    """What a robot at ``round_index`` does when its neighbours are two or more rounds ahead
    (``newest``: each neighbour's credible round; None: no evidence, counted as at our round).

    The target is the quorum's round (:func:`quorum_round`), at most ``last_round``: one
    neighbour alone, however far ahead it says it is, moves nothing. Nothing (None) if that is
    less than two rounds ahead; train through to it (their snapshots stand in meanwhile; no steps
    lost) when that keeps them waiting at most ``max_neighbour_wait_s``; else skip to it. Without
    a measured round time (just started) it skips."""
    target = quorum_round(round_index if r is None else r for r in newest.values())
    if target is None:
        return None
    if last_round is not None:
        target = min(target, last_round)
    if target <= round_index + 1:
        return None
    if round_compute_s is not None and (target - round_index) * round_compute_s <= max_neighbour_wait_s:
        return "train", target
    return "skip", target


class RefusalStreaks:
    """Which neighbours' snapshots were refused, so that the barrier stops waiting for them.

    A refused snapshot of round k or later is that neighbour's answer for round k: bad, but an
    answer; it will not send another, so the barrier of round k does not wait for it. A neighbour
    whose barriers ended ``after`` times in a row with a refusal and nothing accepted is not
    waited for at all, until one of its snapshots is accepted again. Only a network whose
    senders are authenticated (``Network.senders_authenticated``) reports refusals: elsewhere
    anyone can put a bad message on a robot's keys and end the wait for the real one. Thread-safe."""

    def __init__(self, after: int = 3) -> None:
        self.after = after
        self._lock = threading.Lock()
        self._refused: dict[int, int] = {}  # neighbour -> newest round of a refused snapshot
        self._streak: dict[int, int] = {}  # neighbour -> barriers in a row ended refused

    def refused(self, j: int, round_index: int) -> None:
        with self._lock:
            self._refused[j] = max(self._refused.get(j, -1), round_index)

    def not_awaited(self, j: int, round_index: int) -> bool:
        """Whether the barrier of ``round_index`` need not wait for j."""
        with self._lock:
            return (self._refused.get(j, -1) >= round_index
                    or (self.after > 0 and self._streak.get(j, 0) >= self.after))

    def barrier_ended(self, round_index: int, delivered: Iterable[int], awaited: Iterable[int]) -> list[int]:
        """Count the barrier's outcome; the neighbours whose streak reached ``after`` just now."""
        delivered = set(delivered)
        reached = []
        with self._lock:
            for j in set(awaited) | set(self._streak):
                if j in delivered:
                    self._streak.pop(j, None)
                elif self._refused.get(j, -1) >= round_index:
                    self._streak[j] = self._streak.get(j, 0) + 1
                    if self._streak[j] == self.after:
                        reached.append(j)
        return sorted(reached)

    def streaks(self) -> dict[int, int]:
        with self._lock:
            return dict(self._streak)
