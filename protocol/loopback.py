"""An in-memory :class:`protocol.network.Network`: several robots in one process, no sockets.

For tests of the daemon's logic (rounds, joins, alignment, forged messages) without the cost
and the timing noise of real processes; what crosses real links is tested over Zenoh elsewhere.
It keeps Zenoh's semantics where the daemon depends on them: peers do not relay (a robot sees
the tokens and puts of the robots it is linked to only), callbacks run on a thread of the
receiving network (never on the sender's), a ``latest`` query with ``min_round`` gets no reply
until the served round is new enough, and byte counters have the transport's shape::

    hub = LoopbackHub(links=[(1, 2), (2, 3)])        # a line; None: everyone linked
    net = LoopbackNetwork(hub, Keys("lab"), robot_id=2).open()
    hub.cut(2, 3)                                     # a link down: tokens go, puts stop
"""

from __future__ import annotations

import queue
import threading
from collections import defaultdict
from typing import Any, Callable, Iterable

from protocol.keys import ForeignKey, Keys
from protocol.network import Served

__all__ = ["LoopbackHub", "LoopbackNetwork", "key_matches"]


def key_matches(key_expr: str, key: str) -> bool:
    """Zenoh's wildcards on ``/`` chunks: ``*`` is one chunk, ``**`` any number of them."""
    want, have = key_expr.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(want):
            return j == len(have)
        if want[i] == "**":
            return any(match(i + 1, k) for k in range(j, len(have) + 1))
        return j < len(have) and want[i] in ("*", have[j]) and match(i + 1, j + 1)

    return match(0, 0)


class LoopbackHub:
    """The shared medium: which robots are open, which pairs are linked, who holds a token."""

    def __init__(self, links: Iterable[tuple[int, int]] | None = None) -> None:
        self._lock = threading.RLock()
        self._links = None if links is None else {frozenset(l) for l in links}
        self._cut: set[frozenset[int]] = set()
        self._members: dict[int, LoopbackNetwork] = {}
        self._alive: set[int] = set()

    def linked(self, a: int, b: int) -> bool:
        pair = frozenset((a, b))
        with self._lock:
            return a == b or ((self._links is None or pair in self._links) and pair not in self._cut)

    def peers(self, robot_id: int) -> list["LoopbackNetwork"]:
        """The open networks linked to ``robot_id`` (itself included: Zenoh delivers local puts too)."""
        with self._lock:
            return [n for i, n in self._members.items() if self.linked(robot_id, i)]

    def visible_alive(self, robot_id: int) -> frozenset[int]:
        with self._lock:
            return frozenset(i for i in self._alive if i in self._members and self.linked(robot_id, i))

    def cut(self, a: int, b: int) -> None:
        with self._lock:
            self._cut.add(frozenset((a, b)))
        self._tokens_changed()

    def heal(self, a: int, b: int) -> None:
        with self._lock:
            self._cut.discard(frozenset((a, b)))
        self._tokens_changed()

    def _join(self, net: "LoopbackNetwork") -> None:
        with self._lock:
            if net.robot_id in self._members:
                raise ValueError(f"robot {net.robot_id} is already on this hub")
            self._members[net.robot_id] = net

    def _leave(self, robot_id: int) -> None:
        with self._lock:
            self._members.pop(robot_id, None)
            self._alive.discard(robot_id)
        self._tokens_changed()

    def _declare(self, robot_id: int) -> None:
        with self._lock:
            self._alive.add(robot_id)
        self._tokens_changed()

    def _tokens_changed(self) -> None:
        with self._lock:
            members = list(self._members.values())
        for net in members:
            net._alive_changed(self.visible_alive(net.robot_id))


class _Sub:
    def __init__(self, net: "LoopbackNetwork", key_expr: str, callback: Callable) -> None:
        self.net, self.key_expr, self.callback = net, key_expr, callback

    def undeclare(self) -> None:
        self.net._drop(self)


class LoopbackNetwork:
    """One robot's end of a :class:`LoopbackHub` (implements :class:`protocol.network.Network`)."""

    senders_authenticated = True  # one process: every robot puts only on its own keys

    def __init__(self, hub: LoopbackHub, keys: Keys, robot_id: int) -> None:
        keys.alive(robot_id)  # validates the id
        self.hub, self.keys, self.robot_id = hub, keys, robot_id
        self._lock = threading.Lock()
        self._subs: list[_Sub] = []
        self._watchers: list[_Sub] = []
        self._seen_alive: frozenset[int] = frozenset()
        self._served: dict[str, Served] = {}
        self._bytes_out: dict[str, int] = defaultdict(int)
        self._bytes_in: dict[int, int] = defaultdict(int)
        self._messages = {"in": 0, "out": 0}
        self.callback_errors = 0
        self._inbox: queue.Queue = queue.Queue()
        self._open = False
        self._thread = threading.Thread(target=self._dispatch, name=f"loopback-{robot_id}", daemon=True)

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "LoopbackNetwork":
        self.hub._join(self)
        self._open = True
        self._thread.start()
        return self

    def close(self) -> None:
        if not self._open:
            return
        self._open = False
        self.hub._leave(self.robot_id)
        self._inbox.put(None)

    def _dispatch(self) -> None:
        while (job := self._inbox.get()) is not None:
            callback, args = job
            try:
                callback(*args)
            except Exception:  # as ZenohTransport: a callback's error never escapes into the network
                self.callback_errors += 1

    def _deliver(self, callback: Callable, *args: Any) -> None:
        if self._open:
            self._inbox.put((callback, args))

    # ------------------------------------------------------------------ liveliness
    def declare_alive(self) -> None:
        self.hub._declare(self.robot_id)

    def watch_alive(self, callback: Callable[[frozenset[int]], None]) -> _Sub:
        sub = _Sub(self, "alive", callback)
        with self._lock:
            self._watchers.append(sub)
            current = self._seen_alive = self.hub.visible_alive(self.robot_id)
        callback(current)  # as ZenohTransport: the robots already alive are reported at once
        return sub

    def _alive_changed(self, ids: frozenset[int]) -> None:
        with self._lock:
            if ids == self._seen_alive:
                return
            self._seen_alive = ids
            watchers = list(self._watchers)
        for w in watchers:
            self._deliver(w.callback, ids)

    # ------------------------------------------------------------------ pub/sub
    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> _Sub:
        sub = _Sub(self, key_expr, callback)
        with self._lock:
            self._subs.append(sub)
        return sub

    def _drop(self, sub: _Sub) -> None:
        with self._lock:
            for group in (self._subs, self._watchers):
                if sub in group:
                    group.remove(sub)

    def publish(self, key: str, data: bytes, block: bool = True) -> None:
        if not self._open:
            raise RuntimeError("loopback network is closed")
        data = bytes(data)
        with self._lock:
            self._bytes_out[self._kind_of(key)] += len(data)
            self._messages["out"] += 1
        for peer in self.hub.peers(self.robot_id):
            peer._receive(key, data)

    def _receive(self, key: str, data: bytes) -> None:
        with self._lock:
            subs = [s for s in self._subs if key_matches(s.key_expr, key)]
        if subs:
            self._count_in(key, len(data))
        for s in subs:
            self._deliver(s.callback, key, data)

    # ------------------------------------------------------------------ queryables
    def set_latest(self, data: bytes | None, round: int | None = None,
                   deltas: tuple[tuple[int, bytes], ...] = ()) -> None:
        with self._lock:
            self._served[self.keys.latest(self.robot_id)] = Served(data, round, deltas)

    def set_keyframes(self, data: bytes | None) -> None:
        with self._lock:
            self._served[self.keys.keyframes(self.robot_id)] = Served(data)

    def _answer(self, key: str, params: dict[str, str]) -> list[bytes]:
        with self._lock:
            frames = self._served.get(key, Served(None)).answer(params)
            self._bytes_out[self._kind_of(key)] += sum(map(len, frames))
            self._messages["out"] += len(frames)
            return frames

    def query(self, key: str, timeout: float | None = None, block: bool = True) -> bytes | None:
        replies = self.query_all(key, timeout, block, first_only=True)
        return replies[0][1] if replies else None

    def query_all(self, key_expr: str, timeout: float | None = None, block: bool = True,
                  first_only: bool = False) -> list[tuple[str, bytes]]:
        selector, _, query = key_expr.partition("?")
        params = dict(p.split("=", 1) for p in query.split(";") if "=" in p)
        out = []
        for peer in self.hub.peers(self.robot_id):
            if peer is self:
                continue
            for key in peer._served_keys(selector):
                for data in peer._answer(key, params):
                    self._count_in(key, len(data))
                    out.append((key, data))
                    if first_only:
                        return out
        return out

    def _served_keys(self, key_expr: str) -> list[str]:
        with self._lock:
            return [k for k in self._served if key_matches(key_expr, k)]

    # ------------------------------------------------------------------ counters
    def _kind_of(self, key: str) -> str:
        try:
            return self.keys.parse(key).kind
        except ForeignKey:
            return "other"

    def _count_in(self, key: str, n: int) -> None:
        try:
            sender = self.keys.parse(key).robot_id
        except ForeignKey:
            sender = -1
        with self._lock:
            self._bytes_in[sender] += n
            self._messages["in"] += 1

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {"bytes_out": dict(self._bytes_out), "bytes_in": dict(self._bytes_in),
                    "bytes_out_total": sum(self._bytes_out.values()), "bytes_in_total": sum(self._bytes_in.values()),
                    "messages_out": self._messages["out"], "messages_in": self._messages["in"],
                    "callback_errors": self.callback_errors, "foreign_keys": 0}
