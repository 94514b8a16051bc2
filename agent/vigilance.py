"""What a robot says about neighbours it does not trust, in one place: a warning in its log and an
event when a suspicion starts (and a line when it ends), and the current suspects for its
heartbeat (``dinerf-agent status``) and its round record.

The suspicions come from three places: a neighbour's claimed round runs ahead of its pace
(``protocol.evidence.ClaimPace``: the claim is cut to what the pace explains), its models are
clipped or quarantined by the robust consensus (``agent.robust``), its snapshots are refused round
after round (``protocol.evidence.RefusalStreaks``: the barrier stops waiting for it).
"""

from __future__ import annotations

import threading

from agent.robust import ClipNews, NeighbourClipper
from agent.telemetry import Reporter
from protocol.evidence import ClaimPace, RefusalStreaks

__all__ = ["Vigilance"]


class Vigilance:
    """Reports suspicions about neighbours once each, and lists the current ones. Thread-safe."""

    def __init__(self, report: Reporter, pace: ClaimPace, refusals: RefusalStreaks,
                 clipper: NeighbourClipper | None) -> None:
        self.report, self.pace, self.refusals, self.clipper = report, pace, refusals, clipper
        self._lock = threading.Lock()
        self._ahead: set[int] = set()
        self.armed = False  # set by arm() once the robot has joined: claims ahead of it are suspicious from then on

    def arm(self) -> None:
        """The robot has joined: from now on a claim ahead of its pace is suspicious, starting with
        those already heard (a neighbour that claimed too much before the join is named now, not
        at its next heartbeat, which may come when its pace explains it)."""
        self.armed = True
        for j, (claim, _) in sorted(self.pace.ahead_of_pace().items()):
            self._update(j, claim, ahead=True)

    def heard_claim(self, j: int, claim: int, now: float, own_round: int) -> None:
        """A heartbeat of j's (from the network's thread): pace its claim, say when it outruns it
        (once armed: before the robot joined, its neighbours are ahead of it by right)."""
        self._update(j, claim, ahead=self.pace.observe(j, claim, now, own_round) and self.armed)

    def _update(self, j: int, claim: int, ahead: bool) -> None:
        with self._lock:
            started, ended = ahead and j not in self._ahead, not ahead and j in self._ahead
            (self._ahead.add if ahead else self._ahead.discard)(j)
        if started:
            believed = self.pace.credible(j)
            self.report.event("ahead_of_pace", sender=j, claimed=claim, believed=believed,
                              min_round_s=self.pace.min_round_s)
            self.report.warn(f"robot {j} claims round {claim}, further than its pace explains (round {believed} at "
                             f"most): its claim is not believed beyond that (a faulty or hostile robot?)")
        elif ended:
            self.report.say(f"robot {j}'s claimed round {claim} is within its pace again")

    def consensus_news(self, news: list[ClipNews], round_index: int) -> None:
        for n in news:
            self.report.event(n.kind, sender=n.neighbour, rounds=n.rounds, factor=n.factor)
            if n.kind == "clipped_neighbour":
                self.report.warn(f"robot {n.neighbour}'s model was clipped {n.rounds} rounds in a row (to "
                                 f"{n.factor:.2g} of its distance this round): it lies far outside the swarm's "
                                 "normal disagreement (a faulty or hostile robot?)")
            elif n.kind == "erratic_neighbour":
                self.report.warn(f"robot {n.neighbour}'s model has not moved as a training robot's does for "
                                 f"{n.rounds} rounds in a row (standing still: a replay? jumping: noise?): "
                                 "a faulty or hostile robot?")
            elif n.kind == "uncorrelated_neighbour":
                self.report.warn(f"robot {n.neighbour}'s model is unrelated to ours (no correlation, as noise has; "
                                 "honest robots share their initial weights): it is not let in (a faulty or hostile "
                                 "robot, or one started with another init_seed?)")
            elif n.kind == "quarantined":
                self.report.warn(f"robot {n.neighbour} is quarantined from round {round_index}: out of the anchors, "
                                 "duals and barrier until its model is within bound again")
            else:
                self.report.say(f"robot {n.neighbour}'s model has been within bound for {n.rounds} rounds: back in "
                                "consensus")

    def suspects(self) -> dict[int, str]:
        """Neighbour -> why it is not trusted now (protocol.messages.SUSPICIONS), the gravest reason."""
        out: dict[int, str] = {}
        for j, run in self.refusals.streaks().items():
            if run >= self.refusals.after:
                out[j] = "refused"
        with self._lock:
            out.update({j: "ahead_of_pace" for j in self._ahead})
        if self.clipper is not None:  # copies made under the GIL: the training thread changes them
            streak, reason = dict(self.clipper.streak), dict(self.clipper.reason)
            out.update({j: reason.get(j, "clipped") for j, run in streak.items() if run >= self.clipper.cfg.report_after})
            out.update({j: "quarantined" for j in set(self.clipper.quarantined)})
        return dict(sorted(out.items()))
