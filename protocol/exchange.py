"""Exchange policy: how a robot's snapshots reach its neighbours and theirs reach it, per round.

Pure policy over a :class:`protocol.network.Network` (no torch, no Zenoh): one sender and one
puller thread per neighbour, so a slow or cut link delays only that neighbour's copy; the
mailbox of received snapshots; the round barrier (whom it waits for, whom it gives up on,
whose newer snapshot stands in, whose refused snapshots end its wait: ``protocol.evidence``).
The daemon decides what to do with the snapshots; this module only moves and validates them.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from protocol import codec
from protocol.compression import BaseBook, CompressionConfig, SnapshotEncoder
from protocol.evidence import RefusalStreaks
from protocol.keys import Keys
from protocol.membership import LastHeard
from protocol.messages import ModelSpec, Rejected, ThetaSnapshot
from protocol.network import Network
from protocol.rounds import Mailbox

__all__ = ["ExchangeTiming", "SnapshotExchange", "NeighbourSender", "NeighbourPuller", "PullPacing"]

Log = Callable[[str], None]  # a line of the robot's log (the caller prefixes who speaks)
Event = Callable[..., None]  # event(kind, **fields)
Reject = Callable[[str, str], None]  # reject(reason, detail)


class _NewestJobThread:
    """One job at a time on its own thread, keeping only the newest job offered meanwhile.

    A job is for a round; an older job still waiting is replaced by a newer one, since nobody
    wants it any more. Subclasses say what a job does (:meth:`_do`).
    """

    def __init__(self, name: str, log: Log) -> None:
        self._log = log
        self._cond = threading.Condition()
        self._slot: tuple[int, Any] | None = None
        self._not_before = 0.0
        self._busy = False
        self._closed = False
        self.last_seconds = 0.0  # duration of the last job (e.g. how long a link held a put)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, round_index: int, data: Any = None, delay_s: float = 0.0) -> None:
        with self._cond:
            if self._slot is not None and self._slot[0] > round_index:
                return  # a newer job is already waiting
            self._slot = (round_index, data)
            self._not_before = time.monotonic() + delay_s
            self._cond.notify_all()

    def idle(self, timeout: float) -> bool:
        """Wait until nothing is pending or in flight (e.g. before exiting)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._slot is None and not self._busy, timeout)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def _do(self, round_index: int, data: Any) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._slot is not None or self._closed)
                if self._closed:
                    return
                pause = self._not_before - time.monotonic()
                if pause > 0:
                    self._cond.wait(pause)  # an offer meanwhile may replace the slot
                    continue
                round_index, data = self._slot
                self._slot = None
                self._busy = True
            t0 = time.monotonic()
            try:
                self._do(round_index, data)
            except Exception as e:  # the transport is closing, or the link is gone: log, go on
                self._log(f"round {round_index}: {type(e).__name__}: {e}")
            self.last_seconds = time.monotonic() - t0
            with self._cond:
                self._busy = False
                self._cond.notify_all()


#: Refusals that say nothing of the sender's model (a copy out of its round, one not addressed to
#: us): they do not end the barrier's wait for it (``RefusalStreaks``).
_NOT_AN_ANSWER = frozenset({"stale_round", "too_far_ahead", "ahead_of_sender", "bad_kind"})

#: Deltas queued for one neighbour before they are replaced by one full snapshot.
MAX_CHAIN = 64  # deltas queued for one slow link at most (the bytes rule below usually stops it first)


def _worth_chaining(frames: list[tuple[int, bytes]], full_bytes: int) -> bool:
    """Whether these deltas beat the full snapshot: at most :data:`MAX_CHAIN`, fewer bytes."""
    return len(frames) <= MAX_CHAIN and sum(len(f) for _, f in frames) < full_bytes


def _chain(chain: tuple[tuple[int, bytes], ...], delta: tuple[int, bytes], full_bytes: int
           ) -> tuple[tuple[int, bytes], ...]:
    """``chain`` with ``delta`` appended, its oldest frames dropped until it is worth chaining."""
    frames = [*chain, delta]
    while frames and not _worth_chaining(frames, full_bytes):
        frames.pop(0)
    return tuple(frames)


class NeighbourSender(_NewestJobThread):
    """Delivers this robot's newest snapshot to one neighbour.

    A put with congestion control BLOCK can wait on a cut or congested link for seconds; with
    one sender per neighbour (and keys addressed to that neighbour) it delays that neighbour's
    copy only, never the round loop nor the other neighbours. A full snapshot replaces whatever
    waits; a delta is queued behind the frames still waiting, since each is the next one's base,
    until the queue would carry more bytes than the full snapshot (or :data:`MAX_CHAIN` frames):
    then the full one goes instead. On a slow link a fixed short chain meant a full snapshot,
    20 times a delta's bytes, every few rounds, which slowed the link further.
    """

    def __init__(self, net: Network, key_for_round: Callable[[int], str], log: Log) -> None:
        self._net = net
        self._key = key_for_round
        self.bytes_sent = 0  # what this link's puts carried, in all
        super().__init__("sender", log)

    def offer_frames(self, round_index: int, push: bytes, full: bytes, delay_s: float = 0.0) -> None:
        """Send ``push`` for ``round_index``; ``full`` (the same model, lossless) stands in for a chain too long."""
        with self._cond:
            pending = self._slot
            if pending is not None and pending[0] > round_index:
                return
            if push is full or pending is None:
                frames = [(round_index, push)]
            elif _worth_chaining(queued := [*pending[1], (round_index, push)], len(full)):
                frames = queued
            else:
                frames = [(round_index, full)]
            if pending is None or push is full:
                self._not_before = time.monotonic() + delay_s
            self._slot = (round_index, frames)
            self._cond.notify_all()

    def resend(self, round_index: int, push: bytes, full: bytes, delay_s: float) -> None:
        """``push`` of ``round_index`` once more (a link came back), unless that round or a newer
        one is still waiting to go: it will go anyway."""
        with self._cond:
            if self._slot is not None and self._slot[0] >= round_index:
                return
        self.offer_frames(round_index, push, full, delay_s=delay_s)

    def _do(self, round_index: int, data: list[tuple[int, bytes]]) -> None:
        for k, frame in data:
            self._net.publish(self._key(k), frame)
            self.bytes_sent += len(frame)


class NeighbourPuller(_NewestJobThread):
    """Asks one neighbour for its snapshot of a round or later, through its ``latest`` queryable.

    Pushes can be lost: a put made while a link was being re-established found no subscriber,
    and a link can come back one-sided (the far end does not see our subscription; measured
    after a SIGSTOP). So the barrier asks for what is missing. The query runs here, not in the
    round loop: over a link that is dying it waits out its timeout, and that must hold up
    nobody. The neighbour answers only once it has that round, so asking early costs no bytes.
    """

    def __init__(self, pull: Callable[[int], None], log: Log) -> None:
        self._pull = pull
        super().__init__("puller", log)

    def _do(self, round_index: int, data: Any) -> None:
        self._pull(round_index)


class PullPacing:
    """How long the barrier waits for a neighbour's push before asking for the snapshot (a pull).

    Asking too early duplicates a push that is merely slow: on a link with 100 ms and 10% loss,
    pulls after a fixed 2 s made it carry 1.5x the bytes (measured, fault-lossy-link). Asking
    too late leaves a lost push to the barrier deadline. So each neighbour has its own delay:
    doubled (up to ``max_s``) when a pull fetched a round its push delivered too, halved (down
    to ``base_s``) when its push arrives within half the delay or when the push of the round
    pulled before never came (that pull was needed: a one-sided link). Thread-safe.
    """

    def __init__(self, base_s: float, max_s: float) -> None:
        self.base_s = base_s
        self.max_s = max(max_s, base_s)
        self._lock = threading.Lock()
        self._delay: dict[int, float] = {}
        self._pulled: dict[int, int] = {}  # neighbour -> round of its last pulled snapshot
        self._pushed: dict[int, int] = {}  # neighbour -> round of its last pushed snapshot
        self._doubled_for: dict[int, int] = {}  # a round counted once as a wasted pull

    def delay(self, j: int) -> float:
        with self._lock:
            return self._delay.get(j, self.base_s)

    def pulled(self, j: int, round_index: int) -> None:
        with self._lock:
            before = self._pulled.get(j)
            if before is not None and before < round_index and self._pushed.get(j, -1) < before:
                self._halve(j)
            self._pulled[j] = round_index
            self._wasted(j, round_index)

    def pushed(self, j: int, round_index: int, waited_s: float) -> None:
        """A push of ``round_index`` arrived ``waited_s`` after our barrier for it began (0: before)."""
        with self._lock:
            self._pushed[j] = round_index
            if not self._wasted(j, round_index) and waited_s < self._delay.get(j, self.base_s) / 2:
                self._halve(j)

    def _halve(self, j: int) -> None:
        self._delay[j] = max(self.base_s, self._delay.get(j, self.base_s) / 2)

    def _wasted(self, j: int, round_index: int) -> bool:
        if (self._pulled.get(j) == round_index == self._pushed.get(j)
                and self._doubled_for.get(j) != round_index):
            self._doubled_for[j] = round_index
            self._delay[j] = min(2 * self._delay.get(j, self.base_s), self.max_s)
            return True
        return False


@dataclass(frozen=True)
class ExchangeTiming:
    """The clocks of the exchange (the daemon's settings of the same names)."""

    round_timeout_s: float  # the barrier's deadline
    pull_after_s: float  # a missing snapshot is asked for after this (then per PullPacing)
    silent_after_s: float  # a neighbour that sent nothing for this long is not waited for
    join_timeout_s: float  # timeout of a query for a neighbour's newest snapshot
    resend_delay_s: float  # re-push our snapshot this long after a neighbour's link appears
    refused_after: int = 3  # a neighbour whose snapshots were refused this many rounds in a row is not waited for


class SnapshotExchange:
    """This robot's snapshots out, its neighbours' in: push, pull, mailbox and the round barrier."""

    def __init__(self, net: Network, keys: Keys, robot_id: int, neighbours: frozenset[int],
                 mailbox: Mailbox[ThetaSnapshot], last_heard: LastHeard, timing: ExchangeTiming,
                 stop: threading.Event, log: Log, event: Event, reject: Reject,
                 claimed_round: Callable[[int], int | None] = lambda j: None,
                 compression: CompressionConfig | None = None) -> None:
        """claimed_round(j): the round neighbour j says it has completed (its newest heartbeat)."""
        self.net, self.keys, self.robot_id, self.neighbours = net, keys, robot_id, neighbours
        self.mailbox, self.last_heard, self.timing, self._stop = mailbox, last_heard, timing, stop
        self._claimed_round = claimed_round
        self._log, self._event, self._reject = log, event, reject
        self.expect: codec.Expectation | None = None  # None: our model is provisional, take nothing
        self._pacing = PullPacing(timing.pull_after_s, timing.round_timeout_s / 4)
        self.refusals = RefusalStreaks(timing.refused_after)
        self._senders: dict[int, NeighbourSender] = {}
        self._pullers: dict[int, NeighbourPuller] = {}
        self._barrier_began: tuple[int, float] = (-1, 0.0)  # (round, monotonic) of the current barrier
        self.latest: tuple[int, bytes] | None = None  # (round, encoded) last published, lossless
        self._last_push: bytes | None = None  # the push of that round (a delta in the delta modes)
        self._deltas: tuple[tuple[int, bytes], ...] = ()  # (base round, push) leading to ``latest``, served with it
        self.encoder = SnapshotEncoder(compression or CompressionConfig())
        self.bases = BaseBook()  # per neighbour the model its deltas are against

    def seed(self, theta0: Mapping[str, Any]) -> None:
        """Every robot of the swarm starts from the same theta^0: a base both ends hold already,
        so even the first snapshot can be a delta (its digest proves the base is the same)."""
        self.encoder.seed(theta0)
        for j in self.neighbours:
            self.bases.seed(j, theta0)

    def start(self) -> None:
        """Subscribe to every neighbour's snapshots addressed to us; one sender and puller each."""
        me = self.robot_id
        for j in sorted(self.neighbours):
            self.net.subscribe(self.keys.theta_for(j, me), self.on_theta)
            self._senders[j] = NeighbourSender(
                self.net, lambda k, j=j: self.keys.theta(me, k, to=j),
                lambda text, j=j: self._log(f"snapshot to robot {j} not sent: {text}"))
            self._pullers[j] = NeighbourPuller(
                lambda k, j=j: self.pull_latest(j, min_round=k),
                lambda text, j=j: self._log(f"asking robot {j} for its snapshot: {text}"))

    def wait_sent(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` until every sender has delivered what it was given."""
        deadline = time.monotonic() + timeout_s
        for sender in self._senders.values():
            sender.idle(max(deadline - time.monotonic(), 0.0))

    def close(self) -> None:
        for worker in [*self._senders.values(), *self._pullers.values()]:
            worker.close()

    def last_put_seconds(self) -> dict[int, float]:
        return {j: round(s.last_seconds, 3) for j, s in self._senders.items()}

    def bytes_sent(self) -> dict[int, int]:
        """Per neighbour, the snapshot bytes its link carried so far (pushes, not pull replies)."""
        return {j: s.bytes_sent for j, s in self._senders.items()}

    # ------------------------------------------------------------------ out
    def publish(self, msg: ThetaSnapshot, spec: ModelSpec, wire_dtype: str, compression: str) -> None:
        """Encode once; serve the lossless frame as ``latest``, with the deltas that lead to it;
        hand the push to every neighbour's sender."""
        base = self.encoder.public()
        push, full = self.encoder.encode(msg, spec, compression, wire_dtype)
        self._deltas = () if push is full or base is None else _chain(self._deltas, (base[0], push), len(full))
        self.net.set_latest(full, round=msg.round, deltas=self._deltas)
        self.latest = (msg.round, full)
        self._last_push = push
        for sender in self._senders.values():
            sender.offer_frames(msg.round, push, full)

    def link_appeared(self, j: int) -> None:
        """A link (re)appeared: snapshots pushed meanwhile found no subscriber. Push our newest
        again once the new session's subscriptions are through (the barrier pulls theirs). In a
        delta mode that is the delta, not the full snapshot: a neighbour that still holds its
        base (a flap: liveliness lost on a saturated link) takes it; one that lost deltas asks
        for the full one (``base_missing``, a pull). Pushing the full snapshot on every flap put
        16 MB on a 5 Mbit/s link, which held up its keep-alives into the next flap."""
        latest, push = self.latest, self._last_push
        if latest is not None and push is not None and j in self._senders:
            self._senders[j].resend(latest[0], push, latest[1], delay_s=self.timing.resend_delay_s)

    # ------------------------------------------------------------------ in
    def on_theta(self, key: str, data: bytes) -> None:
        expect = self.expect
        if expect is None:
            return  # our spec is provisional until the box is known; the barrier pulls it later
        try:
            parsed = self.keys.parse(key)
            if parsed.receiver != self.robot_id:
                raise Rejected("bad_kind", f"snapshot addressed to robot {parsed.receiver}")
            msg = codec.decode(data, expect, kind="theta", key=parsed)
            self._check_horizon(msg)
            self.last_heard.heard(msg.sender)
            got = self.bases.resolve(msg, expect.spec)
            if got == "missing":  # a lost push, or we restarted: its latest is the full model
                self._event("base_missing", sender=msg.sender, snapshot_round=msg.round)
                if msg.sender in self._pullers:
                    self._pullers[msg.sender].offer(msg.round)
                return
            if got == "old":
                return
            msg = got
            self.mailbox.offer(msg.sender, msg.round, msg)
            barrier_round, began = self._barrier_began
            waited = time.monotonic() - began if msg.round == barrier_round else 0.0
            self._pacing.pushed(msg.sender, msg.round, waited)
        except Rejected as e:
            self._reject(e.reason, f"{key}: {e.detail}")
            if (e.reason not in _NOT_AN_ANSWER and self.net.senders_authenticated and parsed.robot_id in self.neighbours
                    and parsed.round is not None):
                self.refusals.refused(parsed.robot_id, parsed.round)
                self.mailbox.notify()  # the barrier stops waiting for it
        except ValueError as e:  # a foreign key on our subscription
            self._reject("garbage", f"{key}: {e}")

    def _check_horizon(self, msg: ThetaSnapshot) -> None:
        """A pushed snapshot may be at most one round past what its sender last said it has
        completed (its next snapshot races its next heartbeat). Further ahead nobody vouches for
        it, and taken in first it would shut out the real one (the mailbox keeps the first copy):
        refused, and the barrier pulls the real snapshot once the sender says it has it. One round
        past our own newest snapshot is not far ahead: a neighbour may have trained on it while
        its heartbeat is on the way (refusing it cost a full snapshot: the next delta had no base)."""
        last = self.mailbox.last_round
        if last is not None and msg.round > last:
            raise Rejected("too_far_ahead", f"round {msg.round} from {msg.sender}, the last round is {last}")
        claim = self._claimed_round(msg.sender)
        published = self.latest[0] if self.latest is not None else -1  # j may have trained on it already
        horizon = max(self.mailbox.current_round, claim if claim is not None else -1, published) + 1
        if msg.round > horizon:
            raise Rejected("ahead_of_sender", f"round {msg.round} from {msg.sender}, which says it has "
                                              f"completed {claim}")

    def fetch_latest(self, j: int, block: bool = True, min_round: int = 0,
                     at_most: int | None = None) -> ThetaSnapshot | None:
        """Neighbour j's newest snapshot of a round in [``min_round``, ``at_most``], from its
        ``latest`` queryable, validated; None if none came. Should several answers come (a forged
        queryable answers too), the one of the earliest round: joining low costs a catch-up,
        joining at a forged round would cost the whole run. We say which base of j we hold, so a
        neighbour one lost delta behind is answered with the deltas since it, not the full model;
        should they not fit our base after all, we ask once more for the full one."""
        if self.expect is None:
            return None
        held = self.bases.held_round(j)
        msg, unfit = self._fetch(j, block, min_round, at_most, held if held is not None and held >= 0 else None)
        if msg is None and unfit:
            msg, _ = self._fetch(j, block, min_round, at_most, None)
        return msg

    def _fetch(self, j: int, block: bool, min_round: int, at_most: int | None, held: int | None
               ) -> tuple[ThetaSnapshot | None, bool]:
        """(the snapshot, whether a delta came that does not fit our base of j)."""
        replies = self.net.query_all(self.keys.latest_since(j, min_round, held), timeout=self.timing.join_timeout_s,
                                     block=block)
        checked = sorted((m for key, data in replies if (m := self._latest_reply(j, key, data, at_most)) is not None),
                         key=lambda m: m.round)
        ends: dict[int, ThetaSnapshot] = {}  # round -> an answer's newest model, the deltas before it dropped
        unfit = False
        for m in checked:  # oldest first: each delta of a chain is the base of the next
            try:
                got = self.bases.resolve(m, self.expect.spec)
                if got == "missing" and held is None:
                    raise Rejected("unknown_base", f"round {m.round}: a delta where the full snapshot was due")
            except Rejected as e:
                self._reject(e.reason, f"latest of robot {j}: {e.detail}")
                continue
            unfit |= got == "missing"
            if isinstance(got, ThetaSnapshot):
                if m.coded is not None and m.coded.base_round in ends:
                    del ends[m.coded.base_round]
                ends.setdefault(got.round, got)
        return (ends[min(ends)] if ends else None), unfit

    def _latest_reply(self, j: int, key: str, data: bytes, at_most: int | None) -> ThetaSnapshot | None:
        """A reply, decoded and checked; only then may it become j's base (a forged reply of a
        later round taken as the base would make every real delta after it look old)."""
        try:
            if key != self.keys.latest(j):
                raise Rejected("sender_mismatch", f"asked robot {j}'s latest, the reply is on {key[:120]!r}")
            msg = codec.decode(data, self.expect, kind="theta")
            if msg.sender != j:
                raise Rejected("sender_mismatch", f"asked robot {j}, the reply says robot {msg.sender}")
            last = self.mailbox.last_round
            if last is not None and msg.round > last:
                raise Rejected("too_far_ahead", f"round {msg.round}, the last round is {last}")
        except Rejected as e:
            self._reject(e.reason, f"latest of robot {j}: {e.detail}")
            return None
        if at_most is not None and msg.round > at_most:
            return None  # past what j says it has completed: nobody vouches for it
        return msg

    def claimed_round(self, j: int) -> int | None:
        """The round neighbour j says, in its newest heartbeat, that it has completed."""
        return self._claimed_round(j)

    def credible_round(self, j: int, round_index: int) -> int | None:
        """The newest round of j's snapshots we hold, up to what j's own heartbeat says it has
        completed (at least our round k: a round-k snapshot is what the barrier waits for).

        A snapshot from the future alone never ends a wait, stands in for another round, nor
        makes a robot skip rounds: j that passed our round without us says so in its heartbeat.
        """
        claim = self._claimed_round(j)
        return self.mailbox.newest_round(j, at_most=max(round_index, claim if claim is not None else -1))

    def pull_latest(self, j: int, min_round: int) -> None:
        """Fetch neighbour j's newest snapshot into the mailbox if it is not older than min_round."""
        # block=False: the link to j may be dying (see ZenohTransport.query)
        claim = self._claimed_round(j)
        msg = self.fetch_latest(j, block=False, min_round=min_round,
                                at_most=max(min_round, claim if claim is not None else -1))
        if msg is not None and msg.round >= min_round:
            self.offer_quietly(j, msg)
            self._pacing.pulled(j, msg.round)
            self._event("pulled", sender=j, snapshot_round=msg.round, next_pull_after_s=self._pacing.delay(j))

    def offer_quietly(self, sender: int, msg: ThetaSnapshot) -> None:
        try:
            self.mailbox.offer(sender, msg.round, msg)
        except Rejected:
            pass

    # ------------------------------------------------------------------ the barrier
    def barrier(self, round_index: int, reachable: Callable[[], set[int]]) -> tuple[dict[int, ThetaSnapshot], float]:
        """Neighbours' round-k snapshots, waiting until every reachable neighbour answered or the deadline.

        Pushes can be lost, so a neighbour still missing after its pull delay (:class:`PullPacing`)
        is asked for its round-k snapshot, or a later one, in the background
        (:class:`NeighbourPuller`). A neighbour whose newest snapshot is already for a later round
        passed round k without us (its round-k push was lost while the link was down) and waits
        for *our* next snapshot: its newer snapshot stands in for round k, or both sides would
        wait out ``round_timeout_s``. ``reachable()``: the live neighbours whose tokens we see.
        """
        awaited = self._awaited(round_index, reachable)
        t0 = time.monotonic()
        self._barrier_began = (round_index, t0)
        deadline = t0 + self.timing.round_timeout_s
        while True:
            slice_s = max(min(self.timing.pull_after_s, deadline - time.monotonic()), 0.0)
            got = self.mailbox.wait(round_index, awaited, slice_s)
            if got.complete or time.monotonic() >= deadline or self._stop.is_set():
                break
            for j in sorted(got.missing):
                if j in self._pullers and time.monotonic() - t0 >= self._pacing.delay(j):
                    self._pullers[j].offer(round_index)
        got = self.mailbox.wait(round_index, awaited, 0.0)
        waited = time.monotonic() - t0
        for j in self.refusals.barrier_ended(round_index, got.items, reachable()):
            self._event("refused_neighbour", sender=j, rounds=self.refusals.after)
            self._log(f"round {round_index}: every snapshot of robot {j} was refused for {self.refusals.after} rounds "
                      "though it is still heard; not waiting for it until one is accepted")
        if not got.complete:
            self._log(f"round {round_index}: no snapshot from {sorted(got.missing)} "
                      f"within {self.timing.round_timeout_s:.0f} s; going on with {sorted(got.items)}")
        items = dict(got.items)
        for j in reachable() - items.keys():
            r = self.credible_round(j, round_index)
            newest = self.mailbox.newest_item(j, at_most=r) if r is not None else None
            if newest is not None and newest[0] > round_index:
                items[j] = newest[1]
                self._event("ahead", sender=j, snapshot_round=newest[0])
        return {j: items[j] for j in sorted(items) if j in self.neighbours}, waited

    def _awaited(self, round_index: int, reachable: Callable[[], set[int]]) -> Callable[[], set[int]]:
        """Whom the barrier of ``round_index`` waits for: reachable neighbours without a snapshot of
        that round or later, except those silent for ``silent_after_s`` (reported once each) and
        those whose snapshot was refused (``RefusalStreaks``)."""
        given_up: set[int] = set()

        def awaited() -> set[int]:
            missing = {j for j in reachable()
                       if (r := self.credible_round(j, round_index)) is None or r <= round_index}
            missing -= {j for j in missing if self.refusals.not_awaited(j, round_index)}
            silent = self.last_heard.silent(missing, self.timing.silent_after_s)
            for j in silent - given_up:
                given_up.add(j)
                self._event("silent", sender=j, silence_s=round(self.last_heard.silence_s(j), 2))
                self._log(f"round {round_index}: robot {j} sent nothing for "
                          f"{self.timing.silent_after_s:.0f} s though its token is still seen; not waiting for it")
            return missing - silent

        return awaited
