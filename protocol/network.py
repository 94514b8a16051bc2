"""What a robot needs from the network, as a protocol: the seam between transport and daemon.

:class:`protocol.transport.ZenohTransport` implements it over Zenoh and
:class:`protocol.loopback.LoopbackNetwork` in memory (one process, for tests of the daemon's
logic). The daemon only ever talks to this interface, as rmw_zenoh keeps the middleware behind
the ROS 2 client library. Keys are built by :class:`protocol.keys.Keys`; payloads are bytes from
:mod:`protocol.codec`. Callbacks run on the network's threads: keep them short and never call a
blocking method (``query``, ``publish``) from one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol

from protocol.keys import HELD_PARAM, MIN_ROUND_PARAM, min_round_of

__all__ = ["Network", "Handle", "Served"]


@dataclass(frozen=True)
class Served:
    """What one of our queryables holds: ``data`` (of ``round``) and, for ``latest`` in a delta
    mode, the pushes that led to it, so that an asker one lost delta behind gets those deltas
    (tens of KB) instead of the full float32 snapshot (16 MB on lego)."""

    data: bytes | None
    round: int | None = None
    deltas: tuple[tuple[int, bytes], ...] = ()  # (base round, push), oldest first; the last is of ``round``

    def answer(self, params: Mapping[str, str]) -> list[bytes]:
        """The replies to a query with these parameters: nothing while ``round`` is older than
        ``min_round``; the deltas from the asker's ``held`` base when they are fewer bytes than
        ``data``; else ``data``. The asker checks each frame's base and digest (never trusts this)."""
        wanted, held = min_round_of(params.get(MIN_ROUND_PARAM)), min_round_of(params.get(HELD_PARAM))
        if self.data is None or (wanted is not None and self.round is not None and self.round < wanted):
            return []
        starts = [i for i, (base, _) in enumerate(self.deltas) if base == held]
        if held is not None and starts:
            frames = [frame for _, frame in self.deltas[starts[-1]:]]
            if sum(map(len, frames)) < len(self.data):
                return frames
        return [self.data]


class Handle(Protocol):
    """A subscription or watch; ``undeclare`` stops its callbacks."""

    def undeclare(self) -> None: ...


class Network(Protocol):
    #: Whether a message on robot j's keys can only come from robot j (mutual TLS and the roster's
    #: access control): only then does a refused message say anything about robot j.
    senders_authenticated: bool

    def declare_alive(self) -> None:
        """Hold this robot's liveliness token until the network is closed (or the process dies)."""

    def watch_alive(self, callback: Callable[[frozenset[int]], None]) -> Handle:
        """``callback(ids)`` with the full set of robots whose tokens are seen, on every change."""

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Handle:
        """``callback(key, data)`` for every put matching ``key_expr`` (``*`` = one key segment)."""

    def publish(self, key: str, data: bytes, block: bool = True) -> None:
        """Reliable put; ``block=False`` for periodic messages, which may be dropped under congestion."""

    def set_latest(self, data: bytes | None, round: int | None = None,
                   deltas: tuple[tuple[int, bytes], ...] = ()) -> None:
        """Serve our newest snapshot (of ``round``) on ``latest/<id>``, answered by :meth:`Served.answer`."""

    def set_keyframes(self, data: bytes | None) -> None:
        """Serve our keyframe summary on ``keyframes/<id>``."""

    def query(self, key: str, timeout: float | None = None, block: bool = True) -> bytes | None:
        """The first reply to a get on ``key``, or None if nobody answered in time."""

    def query_all(self, key_expr: str, timeout: float | None = None, block: bool = True) -> list[tuple[str, bytes]]:
        """Every ``(key, data)`` reply to a get on ``key_expr`` (the key is the replier's)."""

    def stats(self) -> dict[str, Any]:
        """Traffic counters: ``bytes_in`` {sender: n}, ``bytes_out`` {kind: n}, their totals ..."""

    def close(self) -> None:
        """Leave: the token goes, callbacks stop. Idempotent."""
