"""When a robot's round moves by other means than training: joining the swarm at start (or after a
restart), and catching up with neighbours that went on without it (it was frozen or cut off).

Only a quorum of neighbours moves a robot's round (``protocol.evidence.quorum_round``: the round
a strict majority has reached, never the furthest claim), never past ``training.rounds``, and
during a run never faster than the neighbours' paces explain (the rounds the exchange credits
them with are ``ClaimPace``-bounded; at start there is no pace yet, only the quorum). A robot that moves two or more rounds takes the coordinate-wise median of
the models there (``agent.robust.coordinate_median``, its own voting when they are even in
number), not their mean: one forged model cannot set it. When the robot keeps its own model (an
unaligned robot; ``daemon.adopt_after_rounds = 0``) it never jumps onto the last round: that
round it trains itself, so that ``done.json`` never counts a round the robot neither trained nor
took from a quorum.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Mapping

import numpy as np
import torch
from torch import Tensor

from agent.robust import coordinate_median
from agent.telemetry import Reporter
from agent.trainer import RobotTrainer
from protocol.evidence import plan_catch_up, quorum_round
from protocol.exchange import SnapshotExchange
from protocol.messages import ThetaSnapshot
from protocol.rounds import Mailbox

__all__ = ["RejoinPolicy", "Rejoin", "Move", "to_torch"]


def to_torch(snapshots: Mapping[int, ThetaSnapshot]) -> dict[int, dict[str, Tensor]]:
    return {j: {n: torch.from_numpy(np.array(a, dtype=np.float32, copy=True)) for n, a in m.tensors.items()}
            for j, m in snapshots.items()}


@dataclass(frozen=True)
class RejoinPolicy:
    """The daemon's settings of the same names, and the swarm's last round."""

    rounds: int  # training.rounds
    adopt_after_rounds: int  # this many rounds behind: take the neighbours' model, forget the duals (0 = never)
    round_timeout_s: float  # a gap trained through keeps the neighbours waiting at most half of this
    heartbeat_s: float


@dataclass(frozen=True)
class Move:
    """A round reached by a join or a skip: the daemon publishes, checkpoints and records it."""

    kind: str  # "joined" | "caught_up"
    from_round: int
    to_round: int
    adopted: tuple[int, ...]  # the neighbours whose models were voted on (none: the robot kept its own)
    heard: dict[int, ThetaSnapshot]  # the models there, the next round's anchors

    def record(self) -> dict:
        """As done.json lists it."""
        return {"kind": self.kind, "from": self.from_round, "to": self.to_round, "adopted": list(self.adopted)}


class Rejoin:
    """Joins and catch-ups of one robot (see the module docstring)."""

    def __init__(self, policy: RejoinPolicy, trainer: RobotTrainer, exchange: SnapshotExchange,
                 mailbox: Mailbox[ThetaSnapshot], report: Reporter, stop: threading.Event,
                 peers: Callable[[], set[int]], in_consensus: Callable[[], bool],
                 claimed_round: Callable[[int], int | None]) -> None:
        """peers(): the reachable neighbours in consensus; claimed_round(j): the round j says it
        has completed (the join's evidence; during a run, the exchange's paced rounds decide)."""
        self.policy, self.trainer, self.exchange, self.mailbox, self.report = policy, trainer, exchange, mailbox, report
        self._stop, self.peers, self.in_consensus, self.claimed_round = stop, peers, in_consensus, claimed_round

    # ------------------------------------------------------------------ at start
    def join(self, round_index: int) -> Move | None:
        """Move to the round a quorum of the neighbours has reached, with their models there.

        First the quorum of their claimed rounds (a neighbour that has said nothing counts as at
        ours); then each one's newest snapshot up to that round and its own claim; then the
        quorum of the snapshots' rounds. One claim or answer, forged or not, moves nothing alone,
        and a snapshot past the claims' quorum is never fetched: taken in, it would become that
        neighbour's base, and none of its real deltas would fit it again."""
        claims = {j: self._wait_for_claim(j) for j in sorted(self.peers())}
        bound = max(round_index, quorum_round(round_index if c is None else c for c in claims.values()) or 0)
        newest: dict[int, ThetaSnapshot] = {}
        evidence: dict[int, int] = {}
        for j, claim in claims.items():
            msg = None if claim is None else self.exchange.fetch_latest(j, at_most=min(claim, bound))
            if msg is not None:
                newest[j] = msg
            evidence[j] = msg.round if msg is not None else round_index
        move = None
        target = quorum_round(evidence.values())
        if target is not None and target > round_index:
            fresh = round_index == 0 and self.trainer.step == 0
            # an unaligned robot keeps its own field: the neighbours' lives in a frame it cannot place yet
            adopt = ((fresh or self._is_stale(round_index, target)) and self.in_consensus()
                     and bool(self._voters({j: m for j, m in newest.items() if m.round >= target})))
            target = target if adopt else min(target, self.policy.rounds - 1)
            models = {j: m for j, m in newest.items() if m.round >= target}
            if target > round_index:
                # a new robot starts from the swarm's current model, not from theta^0
                voters = self.adopt(models, reset_duals=not fresh) if adopt else ()
                move = Move("joined", round_index, target, voters, models)
                self.report.event("joined", from_round=round_index, to_round=target, fresh=fresh, adopted=bool(voters),
                                  voters=list(voters), quorum=evidence)
                self.report.say(f"joining the swarm at round {target} (was at {round_index}; neighbours' rounds "
                                f"{evidence}{f', taking the median of {list(voters)} models' if voters else ''})")
                self.mailbox.advance(target)
        for j, m in newest.items():
            if m.round >= self.mailbox.current_round:
                self.exchange.offer_quietly(j, m)
        return move

    def _wait_for_claim(self, j: int) -> int | None:
        """j's claimed round, waiting a few heartbeats for its first status if none came yet."""
        deadline = time.monotonic() + 4 * self.policy.heartbeat_s
        while (claim := self.claimed_round(j)) is None and time.monotonic() < deadline and not self._stop.is_set():
            time.sleep(0.05)
        return claim

    # ------------------------------------------------------------------ during a run
    def catch_up(self, round_index: int, round_compute_s: float | None) -> Move | None:
        """If a quorum of neighbours moved on without us (we were slow or cut off), catch up.

        One neighbour round ahead is normal: it waits at its barrier for our next snapshot. Two or
        more ahead means a quorum passed a barrier without us and waits for our round-``target``
        snapshot. Training through costs no steps; skipping keeps them from timing out round
        after round when training through would take too long (``plan_catch_up``)."""
        credible = {j: self.exchange.credible_round(j, round_index) for j in self.peers()}
        plan = plan_catch_up(round_index, credible, round_compute_s, self.policy.round_timeout_s / 2,
                             last_round=self.policy.rounds)
        if plan is None:
            return None
        action, target = plan
        if action == "train":
            self.report.event("training_through", from_round=round_index, to_round=target)
            return None
        models = {}
        for j, r in credible.items():  # each neighbour's newest model of the target round or later, as far as vouched
            item = self.mailbox.newest_item(j, at_most=r) if r is not None and r >= target else None
            if item is not None and j in self.exchange.neighbours:
                models[j] = item[1]
        adopt = self._is_stale(round_index, target) and self.in_consensus() and bool(self._voters(models))
        if not adopt and target >= self.policy.rounds:
            target = self.policy.rounds - 1  # the last round is trained, never skipped onto
            if target <= round_index + 1:
                return None
            models = {j: m for j, m in models.items() if m.round >= target}
        self.mailbox.advance(target)
        voters = self.adopt(models, reset_duals=True) if adopt else ()
        self.report.event("caught_up", from_round=round_index, to_round=target, adopted=bool(voters),
                          voters=list(voters), quorum=credible)
        self.report.say(f"a quorum of neighbours is at round {target} ({credible}); skipping from {round_index}"
                        f"{f', taking the median of {list(voters)} models' if voters else ''}")
        return Move("caught_up", round_index, target, voters, dict(sorted(models.items())))

    def _is_stale(self, round_index: int, target: int) -> bool:
        return self.policy.adopt_after_rounds > 0 and target - round_index >= self.policy.adopt_after_rounds

    # ------------------------------------------------------------------ models
    def _voters(self, snapshots: Mapping[int, ThetaSnapshot]) -> dict[int, ThetaSnapshot]:
        quarantined = self.trainer.consensus.clipper.quarantined if self.trainer.consensus is not None else set()
        return {j: m for j, m in sorted(snapshots.items()) if j not in quarantined}

    def adopt(self, snapshots: Mapping[int, ThetaSnapshot], reset_duals: bool) -> tuple[int, ...]:
        """Replace theta_i by the coordinate-wise median of the snapshots, the robot's own model
        voting when they are even in number. Neighbours the robust consensus quarantined do not
        vote; without any voter the robot keeps its model. Returns the voters."""
        voters = to_torch(self._voters(snapshots))
        if voters:
            self.trainer.load_theta(coordinate_median(list(voters.values()), own=self.trainer.theta()),
                                    reset_duals=reset_duals)
        return tuple(voters)
