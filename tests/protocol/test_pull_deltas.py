"""Pulls in a delta mode: a receiver one lost delta behind gets the deltas since its base, not the
full float32 snapshot; deltas that do not fit its base fall back to the full one; and a push one
round past our own snapshot is taken before its sender's heartbeat says so (refusing it had made
the next delta baseless, hence a full pull, on every fast link)."""

from __future__ import annotations

import threading
import time

import numpy as np

from protocol import codec
from protocol.compression import CompressionConfig
from protocol.exchange import ExchangeTiming, SnapshotExchange, _chain
from protocol.keys import HELD_PARAM, MIN_ROUND_PARAM, Keys
from protocol.loopback import LoopbackHub, LoopbackNetwork
from protocol.membership import LastHeard
from protocol.messages import ModelSpec, ThetaSnapshot
from protocol.network import Served
from protocol.rounds import Mailbox
from tests.protocol.helpers import ALLOWED, SWARM

RNG = np.random.default_rng(3)
THETA0 = {"grid.table": RNG.standard_normal((4096, 2)).astype(np.float32),
          "mlp.0.weight": RNG.standard_normal((16, 8)).astype(np.float32)}
SPEC = ModelSpec.from_tensors(THETA0)
TIMING = ExchangeTiming(round_timeout_s=5.0, pull_after_s=0.2, silent_after_s=3.0, join_timeout_s=2.0,
                        resend_delay_s=0.1)


def _expect() -> codec.Expectation:
    return codec.Expectation(SWARM, SPEC, allowed_senders=ALLOWED)


def _trained(theta: dict[str, np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """theta after a round: a few entries move (what a round of hash-grid training touches)."""
    out = {}
    for n, a in theta.items():
        d = rng.standard_normal(a.shape).astype(np.float32) * 0.05
        d[rng.random(a.shape) > 0.05] = 0
        out[n] = (a + d).astype(np.float32)
    return out


def test_served_latest_answers_the_deltas_from_the_askers_base_when_they_are_fewer_bytes():
    full, deltas = b"F" * 100, ((4, b"d5" * 10), (5, b"d6" * 10), (6, b"d7" * 10))
    served = Served(full, 7, deltas)
    assert served.answer({}) == [full]  # a plain query: the full snapshot
    assert served.answer({HELD_PARAM: "5"}) == [b"d6" * 10, b"d7" * 10]
    assert served.answer({HELD_PARAM: "4", MIN_ROUND_PARAM: "7"}) == [d for _, d in deltas]
    assert served.answer({HELD_PARAM: "3"}) == [full]  # not in the chain
    assert served.answer({HELD_PARAM: "x"}) == [full]  # malformed: a plain query
    assert served.answer({HELD_PARAM: "5", MIN_ROUND_PARAM: "8"}) == []  # not that far yet
    assert Served(b"F" * 30, 7, deltas).answer({HELD_PARAM: "4"}) == [b"F" * 30]  # deltas outweigh it
    assert Served(None).answer({HELD_PARAM: "4"}) == []


def test_the_served_chain_never_outweighs_the_full_snapshot():
    chain: tuple[tuple[int, bytes], ...] = ()
    for r in range(10):
        chain = _chain(chain, (r, b"x" * 30), 100)
        assert sum(len(f) for _, f in chain) < 100 and chain[-1][0] == r
    assert [b for b, _ in chain] == [7, 8, 9]


class _Pair:
    """Robot 1 publishes, robot 2 receives, over the in-memory network."""

    def __init__(self) -> None:
        self.hub = LoopbackHub(links=[(1, 2)])
        keys = Keys(SWARM)
        self.nets = {i: LoopbackNetwork(self.hub, keys, i).open() for i in (1, 2)}
        self.stop, self.events, self.rejected = threading.Event(), [], []
        cfg = CompressionConfig(compression="delta+quinary")
        self.ex = {i: SnapshotExchange(self.nets[i], keys, i, frozenset({3 - i}), Mailbox(max_ahead=4), LastHeard(),
                                       TIMING, self.stop, lambda s: None,
                                       lambda kind, **f: self.events.append((kind, f)),
                                       lambda r, d: self.rejected.append((r, d)), compression=cfg) for i in (1, 2)}
        for e in self.ex.values():
            e.expect = _expect()
            e.seed(THETA0)
            e.start()
        self.theta, self.rng = dict(THETA0), np.random.default_rng(7)
        self.claim = 0  # the round robot 1's newest heartbeat says it has completed
        self.ex[2]._claimed_round = lambda j: self.claim

    def publish(self, r: int, lost: bool = False) -> None:
        """Robot 1's snapshot of round r; ``lost``: its push goes nowhere (the link is cut meanwhile)."""
        self.theta = _trained(self.theta, self.rng)
        if lost:
            self.hub.cut(1, 2)
        self.claim = r
        self.ex[1].publish(ThetaSnapshot(SWARM, 1, r, 0, SPEC.signature(), self.theta), SPEC, "float32", "zstd")
        self.ex[1].wait_sent(5.0)
        if lost:
            self.hub.heal(1, 2)

    def received(self, r: int) -> ThetaSnapshot:
        got = self.ex[2].mailbox.wait(r, lambda: {1}, 5.0)
        assert got.complete, (f"round {r} never arrived", self.events, self.rejected)
        self.ex[2].mailbox.advance(r)  # robot 2 went on to the next round
        return got.items[1]

    def through_a_lost_delta(self, before_loss=lambda: None) -> tuple[ThetaSnapshot, int]:
        """Rounds 1 and 2 delivered, round 3's push lost, round 4 published (its base is missing:
        robot 2 pulls, saying it holds round 2): robot 2's round 4 and the bytes it took for it."""
        for r in (1, 2):
            self.publish(r)
            self.received(r)
        before_loss()
        self.publish(3, lost=True)
        before = self.latest_bytes_in()
        self.publish(4)
        got = self.received(4)
        return got, self.latest_bytes_in() - before

    def latest_bytes_in(self) -> int:
        return self.nets[2].stats()["bytes_in"].get(1, 0)

    def close(self) -> None:
        self.stop.set()
        for e in self.ex.values():
            e.close()
        for n in self.nets.values():
            n.close()


def _until(done, timeout_s: float = 5.0) -> bool:
    """Wait for what the network's delivery thread does after a put returned."""
    deadline = time.monotonic() + timeout_s
    while not done() and time.monotonic() < deadline:
        time.sleep(0.01)
    return done()


def _same_as_published(pair: _Pair, got: ThetaSnapshot) -> bool:
    want = codec.decode(pair.ex[1].latest[1], _expect(), kind="theta").tensors
    return all(got.tensors[n].tobytes() == want[n].tobytes() for n in want)


def test_a_lost_delta_is_made_good_by_the_deltas_since_the_receivers_base():
    pair = _Pair()
    try:
        got, pulled_and_pushed = pair.through_a_lost_delta()
        assert _same_as_published(pair, got)
        kinds = lambda: [k for k, _ in pair.events]  # noqa: E731
        assert _until(lambda: kinds().count("pulled") == 1) and kinds().count("base_missing") == 1, pair.events
        full = len(pair.ex[1].latest[1])
        assert pulled_and_pushed < full / 3, (pulled_and_pushed, full)  # 3 deltas, no full snapshot
        assert pair.ex[2].bases.held_round(1) == 4 and not pair.rejected
        pair.publish(5)  # and the chain goes on from there
        assert _same_as_published(pair, pair.received(5))
    finally:
        pair.close()


def test_deltas_that_do_not_fit_the_receivers_base_fall_back_to_the_full_snapshot():
    pair = _Pair()
    try:
        def replace_the_base() -> None:
            # robot 2's copy of round 2 is not robot 1's (as after a forged plain frame of that
            # round): the deltas since round 2 name a base digest it does not hold
            other = {n: a + 1.0 for n, a in pair.ex[2].bases.resolve(pair.received(2), SPEC).tensors.items()}
            pair.ex[2].bases.resolve(ThetaSnapshot(SWARM, 1, 2, 0, SPEC.signature(), other), SPEC)

        got, took = pair.through_a_lost_delta(before_loss=replace_the_base)
        assert _same_as_published(pair, got)
        assert took > len(pair.ex[1].latest[1])  # the full snapshot came
        assert not pair.rejected, pair.rejected
    finally:
        pair.close()


def test_a_push_one_round_past_our_own_snapshot_is_taken_before_the_senders_heartbeat():
    """Robot 1 waits in its barrier of round 1; robot 2 had its round-1 snapshot, trained round 2
    and pushed it before its heartbeat of round 1 arrived. Taken, not refused as too far ahead;
    two rounds past ours (nobody vouches for that) is still refused."""
    pair = _Pair()
    try:
        me, peer = pair.ex[1], pair.ex[2]
        me._claimed_round = lambda j: 0  # robot 2's newest heartbeat: round 0
        pair.publish(1)  # robot 1's round 1 (mailbox still at round 0, in the barrier)
        rng = np.random.default_rng(11)
        theta = dict(THETA0)
        for r in (1, 2, 4):
            theta = _trained(theta, rng)
            peer.publish(ThetaSnapshot(SWARM, 2, r, 0, SPEC.signature(), theta), SPEC, "float32", "zstd")
            peer.wait_sent(5.0)
        assert _until(lambda: pair.rejected), "the round-4 push never arrived"
        assert me.mailbox.newest_round(2) == 2, pair.events
        assert [r for r, _ in pair.rejected] == ["ahead_of_sender"], pair.rejected  # the round-4 one
    finally:
        pair.close()
