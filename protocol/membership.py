"""Who is in the swarm, who my live neighbours are, and who the reference is.

:class:`Topology` is the static graph from the swarm config (who may talk to whom);
:class:`Membership` combines it with the liveliness tokens seen on the network::

    topo = Topology.from_spec("ring", [0, 1, 2, 3])
    topo.neighbours(0)                 # frozenset({1, 3})
    m = Membership(topo, self_id=1)
    m.update({0, 1, 2})                # True: changed
    m.live_neighbours                  # frozenset({0, 2})
    m.reference                        # 0: lowest live id (self included)
    m.epoch                            # 1: grows by one on every change of the alive set

The reference fixes the gauge of the shared frame; when it dies the lowest survivor takes over
(it freezes its current pose estimate: that is the daemon's job). ``events`` records
``(monotonic time, epoch, alive, reference)`` on each change, to measure failover time.

The epoch is local to this robot (a robot started late begins at 0); it orders *this robot's*
view of membership and is sent in message headers for diagnosis, not for agreement.

Pure Python, thread-safe (``update`` is called from Zenoh callbacks).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Iterable, NamedTuple

TOPOLOGY_KINDS = ("full", "ring", "star", "line", "edges")


class TopologyError(ValueError):
    """An invalid topology specification."""


@dataclass
class TopologyConfig:
    """The ``[topology]`` table of swarm.toml and scenario.toml: which robots talk to which."""

    kind: str = "full"  # full | ring | star | line | edges
    edges: list[list[int]] | None = None  # for "edges": [[1, 2], [2, 3]]
    hub: int | None = None  # for "star" (default: the lowest id)

    def build(self, ids: Iterable[int]) -> "Topology":
        return Topology.from_spec(self.kind, ids, self.edges, self.hub)


@dataclass(frozen=True)
class Topology:
    """An undirected graph over robot ids. Build with :meth:`from_spec`."""

    ids: tuple[int, ...]
    edges: tuple[tuple[int, int], ...]  # sorted (low, high) pairs, sorted list
    kind: str = "edges"

    @classmethod
    def from_spec(cls, kind: str, ids: Iterable[int], edges: Iterable[Iterable[int]] | None = None,
                  hub: int | None = None) -> "Topology":
        """Build a topology.

        - ``full``: every pair;
        - ``ring``: ids in the given order, each to the next and the last to the first (>= 3 ids);
        - ``line``: ids in the given order, each to the next;
        - ``star``: ``hub`` (default: the lowest id) to every other id;
        - ``edges``: the given list of pairs.
        """
        ids = list(ids)
        for i in ids:
            if type(i) is not int or i < 0:
                raise TopologyError(f"robot ids must be non-negative integers, got {i!r}")
        if not ids:
            raise TopologyError("a topology needs at least one robot id")
        if len(set(ids)) != len(ids):
            dups = sorted({i for i in ids if ids.count(i) > 1})
            raise TopologyError(f"duplicate robot ids {dups}")
        if kind not in TOPOLOGY_KINDS:
            raise TopologyError(f"unknown topology kind {kind!r}; use one of {', '.join(TOPOLOGY_KINDS)}")
        if edges is not None and kind != "edges":
            raise TopologyError(f"an edge list is only used with kind 'edges', not {kind!r}")
        if hub is not None and kind != "star":
            raise TopologyError(f"a hub is only used with kind 'star', not {kind!r}")

        pairs: list[tuple[int, int]] = []
        if kind == "full":
            pairs = [(a, b) for n, a in enumerate(ids) for b in ids[n + 1 :]]
        elif kind == "line":
            pairs = list(zip(ids, ids[1:]))
        elif kind == "ring":
            if len(ids) < 3:
                raise TopologyError(f"a ring needs at least 3 robots, got {len(ids)}; use 'line' or 'full'")
            pairs = list(zip(ids, ids[1:] + ids[:1]))
        elif kind == "star":
            centre = min(ids) if hub is None else hub
            if centre not in ids:
                raise TopologyError(f"star hub {centre!r} is not one of the robot ids {ids}")
            pairs = [(centre, i) for i in ids if i != centre]
        else:
            if edges is None:
                raise TopologyError("kind 'edges' needs an edge list, e.g. [[0, 1], [1, 2]]")
            known = set(ids)
            for e in edges:
                e = list(e)
                if len(e) != 2:
                    raise TopologyError(f"an edge is a pair of robot ids, got {e!r}")
                a, b = e
                for x in (a, b):
                    if x not in known:
                        raise TopologyError(f"edge {e} names robot {x!r}, which is not one of {ids}")
                if a == b:
                    raise TopologyError(f"self loop on robot {a}")
                pairs.append((a, b))
        normalised = sorted({(min(a, b), max(a, b)) for a, b in pairs})
        return cls(tuple(sorted(ids)), tuple(normalised), kind)

    def neighbours(self, robot_id: int) -> frozenset[int]:
        if robot_id not in self.ids:
            raise TopologyError(f"robot {robot_id!r} is not in the topology {list(self.ids)}")
        return frozenset(b if a == robot_id else a for a, b in self.edges if robot_id in (a, b))

    def is_connected(self, among: Iterable[int] | None = None) -> bool:
        """Whether the graph restricted to ``among`` (default: all ids) is connected."""
        nodes = set(self.ids if among is None else among) & set(self.ids)
        if not nodes:
            return True
        start = min(nodes)
        seen, todo = {start}, [start]
        while todo:
            x = todo.pop()
            for y in self.neighbours(x) & nodes:
                if y not in seen:
                    seen.add(y)
                    todo.append(y)
        return seen == nodes


class MembershipEvent(NamedTuple):
    """One change of the alive set (a tuple: time, epoch, alive, reference)."""

    time: float  # time.monotonic() when the change was seen
    epoch: int
    alive: frozenset[int]
    reference: int


class Membership:
    """This robot's view of who is alive, its live neighbours and the reference."""

    def __init__(self, topology: Topology, self_id: int):
        if self_id not in topology.ids:
            raise TopologyError(f"robot {self_id!r} is not in the topology {list(topology.ids)}")
        self.topology = topology
        self.self_id = self_id
        self._neighbours = topology.neighbours(self_id)
        self._lock = threading.Lock()
        self._alive = frozenset({self_id})
        self._epoch = 0
        self._events: list[MembershipEvent] = [MembershipEvent(time.monotonic(), 0, self._alive, self_id)]
        self.ignored: set[int] = set()  # ids seen alive that are not in the topology

    def update(self, alive: Iterable[int]) -> bool:
        """Set the ids seen alive (self is always alive; unknown ids are ignored). True if changed."""
        seen = set(alive)
        known = frozenset(seen & set(self.topology.ids)) | {self.self_id}
        with self._lock:
            self.ignored |= seen - set(self.topology.ids)
            if known == self._alive:
                return False
            self._alive = known
            self._epoch += 1
            self._events.append(MembershipEvent(time.monotonic(), self._epoch, known, min(known)))
            return True

    @property
    def alive(self) -> frozenset[int]:
        with self._lock:
            return self._alive

    @property
    def live_neighbours(self) -> frozenset[int]:
        with self._lock:
            return self._alive & self._neighbours

    @property
    def neighbours(self) -> frozenset[int]:
        """Neighbours from the topology, alive or not (whom to subscribe to)."""
        return self._neighbours

    @property
    def reference(self) -> int:
        with self._lock:
            return min(self._alive)

    @property
    def is_reference(self) -> bool:
        return self.reference == self.self_id

    @property
    def epoch(self) -> int:
        with self._lock:
            return self._epoch

    @property
    def events(self) -> list[MembershipEvent]:
        with self._lock:
            return list(self._events)


class AliveView:
    """Who is alive anywhere in the swarm, from direct tokens plus relayed evidence.

    Zenoh peers do not relay for each other, so a robot sees the liveliness tokens of its
    direct peers only; in a line or a star it could not tell whether the lowest id (the
    reference) is alive. Each robot therefore reports in its Status how long ago it last had
    evidence of each robot (``report``); receivers turn ages into times on their own clock
    (``merge``) and keep the freshest. Ages only grow as they travel, so a dead robot's
    evidence expires everywhere ``expiry_s`` after its last neighbour lost its token; a token
    seen leaving overrides relayed evidence older than the departure.

    Times are ``time.monotonic()`` of this process; pass ``now`` explicitly in tests.
    """

    def __init__(self, self_id: int, expiry_s: float = 2.0, departure_grace_s: float = 1.0):
        if expiry_s <= 0 or departure_grace_s < 0:
            raise ValueError("expiry_s must be positive and departure_grace_s non-negative")
        self.self_id = self_id
        self.expiry_s = expiry_s
        # A report sent just before a departure can arrive just after it: relayed evidence must be
        # this much newer than a departure we saw ourselves before it counts.
        self.departure_grace_s = departure_grace_s
        self._lock = threading.Lock()
        self._direct: frozenset[int] = frozenset()
        self._last_seen: dict[int, float] = {}  # freshest evidence (monotonic time)
        self._left_at: dict[int, float] = {}  # when a direct token vanished

    def set_direct(self, ids: Iterable[int], now: float | None = None) -> None:
        """The ids whose liveliness tokens this robot sees right now."""
        now = time.monotonic() if now is None else now
        ids = frozenset(ids) - {self.self_id}
        with self._lock:
            for gone in self._direct - ids:
                self._left_at[gone] = now
                self._last_seen.pop(gone, None)  # we saw it leave: stop vouching at once
            for i in ids:
                self._last_seen[i] = now
            self._direct = ids

    def merge(self, ages: dict[int, float], now: float | None = None) -> None:
        """Evidence relayed by a neighbour: {id: seconds since it was last seen alive}."""
        now = time.monotonic() if now is None else now
        with self._lock:
            for i, age in ages.items():
                if i == self.self_id or i in self._direct:
                    continue
                seen = now - max(float(age), 0.0)
                left = self._left_at.get(i, float("-inf")) + self.departure_grace_s
                if seen > left and seen > self._last_seen.get(i, float("-inf")):
                    self._last_seen[i] = seen

    @property
    def direct(self) -> frozenset[int]:
        """Robots whose tokens this robot sees itself: the ones it can actually exchange with."""
        with self._lock:
            return self._direct

    def alive(self, now: float | None = None) -> frozenset[int]:
        now = time.monotonic() if now is None else now
        with self._lock:
            fresh = {i for i, t in self._last_seen.items() if i in self._direct or now - t < self.expiry_s}
            return frozenset(fresh | self._direct | {self.self_id})

    def report(self, now: float | None = None) -> dict[int, float]:
        """What to gossip: {id: age in seconds} for every robot currently believed alive."""
        now = time.monotonic() if now is None else now
        alive = self.alive(now)
        with self._lock:
            return {
                i: 0.0 if i == self.self_id or i in self._direct else max(now - self._last_seen[i], 0.0)
                for i in alive
            }


class LastHeard:
    """When each direct peer last sent us anything (a heartbeat, a snapshot) or reappeared.

    A liveliness token is not proof that a peer can deliver: behind a cut link Zenoh dropped the
    token of a peer 11 s and 21 s after the cut, with a 1 s lease (a CI run of the cut e2e test;
    probably Zenoh's 10 s SO_LINGER on sockets that still held unsent data, not confirmed), and
    the barrier waited for it all that time. A peer silent for longer than a few heartbeats is not worth waiting for, whatever
    its token says. Times are ``time.monotonic()``; pass ``now`` in tests. Thread-safe.
    """

    def __init__(self, since: float | None = None):
        self._since = time.monotonic() if since is None else since  # a peer never heard counts from here
        self._lock = threading.Lock()
        self._at: dict[int, float] = {}

    def heard(self, peer: int, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            self._at[peer] = max(now, self._at.get(peer, now))

    def silence_s(self, peer: int, now: float | None = None) -> float:
        """Seconds since ``peer`` was last heard (since this clock started if never)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return max(now - self._at.get(peer, self._since), 0.0)

    def silent(self, peers: Iterable[int], after_s: float, now: float | None = None) -> frozenset[int]:
        """The ``peers`` not heard for ``after_s`` seconds or more."""
        now = time.monotonic() if now is None else now
        return frozenset(j for j in peers if self.silence_s(j, now) >= after_s)
