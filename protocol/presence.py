"""Presence: who is alive, who can deliver, who leads, told by tokens, heartbeats and gossip.

Zenoh peers do not relay, so a robot sees only its direct peers' liveliness tokens; every
heartbeat (a :class:`protocol.messages.Status`) therefore carries the sender's evidence of who
is alive (:class:`protocol.membership.AliveView`), and the union decides the reference. A token
is not proof that a peer can deliver (:class:`protocol.membership.LastHeard`): the barrier also
asks whether a peer was heard lately. Pure Python over a :class:`protocol.network.Network`.
"""

from __future__ import annotations

import threading
from typing import Callable

from protocol import codec
from protocol.keys import Keys
from protocol.membership import AliveView, LastHeard, Membership, Topology
from protocol.messages import Rejected, Status
from protocol.network import Network

__all__ = ["Presence"]


class Presence:
    """Membership of one robot, kept current from the network, and its heartbeat."""

    def __init__(self, net: Network, keys: Keys, robot_id: int, topology: Topology, alive_expiry_s: float,
                 heartbeat_s: float, stop: threading.Event, status: Callable[[], Status],
                 on_status: Callable[[Status], None], on_link: Callable[[int], None],
                 on_change: Callable[[Membership], None], log: Callable[[str], None],
                 reject: Callable[[str, str], None]) -> None:
        self.net, self.keys, self.robot_id, self.heartbeat_s, self._stop = net, keys, robot_id, heartbeat_s, stop
        self.membership = Membership(topology, robot_id)
        self.alive = AliveView(robot_id, alive_expiry_s)
        self.last_heard = LastHeard()
        self._status, self._on_status, self._on_link, self._on_change = status, on_status, on_link, on_change
        self._log, self._reject = log, reject
        self._expect = codec.Expectation(swarm=keys.swarm, allowed_senders=frozenset(topology.ids))
        self._thread: threading.Thread | None = None
        self._beat = threading.Event()

    def start(self) -> None:
        """Declare our token, watch everyone's, listen to the neighbours' heartbeats, start ours."""
        self.net.declare_alive()
        self.net.watch_alive(self._tokens)
        for j in sorted(self.membership.neighbours):
            self.net.subscribe(self.keys.status(j), self._heard_status)
        self._thread = threading.Thread(target=self._heartbeat, name="heartbeat", daemon=True)
        self._thread.start()

    def beat_now(self) -> None:
        """Send the next heartbeat now: our round changed. A neighbour holding our newer snapshot
        counts it only once a heartbeat vouches for the round (``SnapshotExchange.credible_round``);
        waiting out the period cost it up to ``heartbeat_s`` per round."""
        self._beat.set()

    def join(self) -> None:
        """Wait for the heartbeat to end (after ``stop`` is set)."""
        self._beat.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * self.heartbeat_s + 1)

    def reachable(self) -> set[int]:
        """Live neighbours whose tokens we see directly: only they can deliver (gossip says who is
        alive somewhere, e.g. behind a cut link, which matters for the reference, not here)."""
        return set(self.membership.live_neighbours & self.alive.direct)

    def refresh(self) -> None:
        if self.membership.update(self.alive.alive()):
            self._on_change(self.membership)

    def _tokens(self, ids: frozenset[int]) -> None:
        before = self.alive.direct
        self.alive.set_direct(ids)
        for j in ids - before:
            self.last_heard.heard(j)  # a token (re)appearing is news from it too
        for j in (ids - before) & self.membership.neighbours:
            self._on_link(j)
        self.refresh()

    def _heard_status(self, key: str, data: bytes) -> None:
        try:
            msg = codec.decode(data, self._expect, kind="status", key=self.keys.parse(key))
        except Rejected as e:
            self._reject(e.reason, f"{key}: {e.detail}")
            return
        except ValueError as e:
            self._reject("garbage", f"{key}: {e}")
            return
        self.last_heard.heard(msg.sender)
        self.alive.merge(msg.alive_ages)
        self._on_status(msg)

    def _heartbeat(self) -> None:
        while not self._stop.is_set():
            try:
                self.refresh()
                self.net.publish(self.keys.status(self.robot_id), codec.encode(self._status()), block=False)
            except Exception as e:  # never let telemetry kill the robot
                self._log(f"heartbeat failed: {type(e).__name__}: {e}")
            self._beat.wait(self.heartbeat_s)
            self._beat.clear()
