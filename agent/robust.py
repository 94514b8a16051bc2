"""Robust consensus: no neighbour's model enters a robot's anchors and duals further than the
swarm's normal disagreement allows, and a robot that replaces its model takes a vote, not a mean.

**Self-centred clipping** (as ClippedGossip, He, Karimireddy and Jaggi 2022). C-ADMM pulls robot i
towards ``(theta_i + theta_j) / 2`` and integrates ``theta_i - theta_j`` into the dual of edge ij,
so a neighbour sending 1e30, -10 theta or noise steers i as far as it likes, and its Adam state
(the second moment of a 1e25 gradient) silences i's own data for thousands of steps. Here, per
tensor t, robot i measures ``d_jt = ||theta_jt - theta_it||`` and moves every neighbour's model to
within ``tau_t`` of its own: ``theta_jt <- theta_it + min(1, tau_t / d_jt) (theta_jt - theta_it)``,
in the anchors; a clipped tensor adds nothing to the dual of its edge (the dual integrates the pull
round after round, and a bounded pull integrated is unbounded). The bound is ``clip_factor``
times the normal disagreement, plus twice i's own movement in the round (two honest models drift
apart by at most what both moved). The normal disagreement is the largest of (a) the normal of the
last ``window`` rounds, (b) this round's vote, the lower median of the neighbours' distances, when
at least two vote, and (c) a floor relative to the tensor's norm; before any round is remembered,
i's own movement in its first round stands for (a). The normal of a round is its vote (one neighbour's distance, with
one), but at most the normal before it plus twice i's own movement: it follows honest robots as
they learn, while a model far outside cannot raise the bar by itself. Per tensor,
because a tensor's scale is its own (a hash table and an MLP bias differ by orders of
magnitude), and adaptive, because disagreement grows and shrinks as the robots learn. Tensors
of fewer than ``SMALL_TENSOR`` values (biases) are measured together, as one: so few values are
no evidence of anything (``SMALL_TENSOR``'s comment says what they did on lego).

Nothing changes without an attack: an honest neighbour within the bound enters exactly as
before (the same tensors, bit for bit), so the figures of every honest run stay what they were.
Both ends of an honest edge clip nothing, so their duals stay exactly opposite (y_ij = -y_ji).

**A model that does not move like a training robot's.** A model inside the normal disagreement
cannot be told from an honest one by where it is, but by how it moves: an honest neighbour's
model moves from one round to the next about as much as the robot's own (0.82-1.22 times on the
tests' scene, 0.93-1.07 on the quickstart's); a replayed old model does not move at all, noise
jumps every round. One whose movement is outside ``move_band`` (4) of ours is erratic.

**A model unrelated to ours.** Every robot starts from the same theta^0 (``init_seed``) and
consensus pulls them together, so an honest neighbour's model correlates with ours (Pearson r of
0.3-1.0 per tensor in the benchmarks' runs, a z-score ``r sqrt(n)`` over 100 for the hash table); noise of the
model's scale does not (z about N(0, 1)), whatever its distance, and -10 theta anticorrelates.
Tensors of n >= (2 ``min_correlation_z``)^2 values are judged (biases are too small to show it):
when most have a z under ``min_correlation_z``, the model enters as our own (as a clipped one at
factor 0), and the neighbour is odd at once, as a gross clip is. Judged whole, not per tensor:
an honest robot that trained apart for rounds was seen with its hash table anticorrelated with
its neighbours' (z -97) while its decoders still correlated (z 22-32). The distance and movement tests
scale with how fast the robots learn (noise of the model's scale passes both while the field
learns fast); this one does not.

**Reporting and quarantine.** A neighbour clipped or erratic ``report_after`` rounds in a row, or
clipped once grossly (further than ``clip_factor`` times the bound), is reported. With at least two
neighbours, one of which is within the bound (the vote says the normal is not what this one
shows), it is also quarantined (``quarantine``): out of the anchors and duals, its edge dual
dropped, not waited for by the barrier. Its snapshots are still measured; within the
bound ``readmit_after`` rounds in a row, it comes back. With one neighbour there is nothing to
vote with: it is clipped and reported, never quarantined.

**Adopting a model** (a join, a catch-up, an aligned robot entering consensus): the
coordinate-wise median of the neighbours' models (BRIDGE's rule), with the robot's own model as
a tie-breaking vote when the neighbours are even in number: one forged model among two cannot
move a coordinate past both honest values.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Mapping, Sequence

import torch
from torch import Tensor

from agent.config_io import check

__all__ = ["RobustConfig", "NeighbourClipper", "ClipNews", "coordinate_median"]


@dataclass
class RobustConfig:
    """``[training.consensus.robust]``: how far a neighbour's model may be from this robot's own."""

    enabled: bool = True  # off: every neighbour's model enters as it came (one robot can steer the others)
    clip_factor: float = 4.0  # a model may lie this many times the normal disagreement away, per tensor
    window: int = 4  # rounds of normal disagreement remembered (honest disagreement swings ~5x round to round)
    floor: float = 1e-3  # the least normal disagreement, relative to the tensor's norm (no history yet)
    # A neighbour's model must move, from one round to the next, between 1/move_band and move_band
    # times what this robot's did (honest robots: 0.82-1.22 on the tests' scene, 0.93-1.07 on the
    # quickstart's): a replayed model does not move at all, noise jumps every round.
    move_band: float = 4.0
    # A tensor of a neighbour's model must correlate with ours at least this many standard errors
    # (Pearson r times sqrt(size)): honest ones measure 15-240 on the tests' scene, noise ~N(0, 1). 0: off.
    min_correlation_z: float = 5.0
    report_after: int = 3  # rounds in a row clipped or erratic before a neighbour is reported (and quarantined)
    quarantine: bool = True  # ... left out of consensus, with at least two neighbours to vote
    readmit_after: int = 3  # rounds in a row within the bound before a quarantined neighbour comes back

    def __post_init__(self) -> None:
        check(self, clip_factor="> 1", window=">= 1", floor="> 0", move_band="> 1", min_correlation_z=">= 0",
              report_after=">= 1", readmit_after=">= 1")


@dataclass(frozen=True)
class ClipNews:
    """Something an operator should hear about a neighbour (the daemon logs it and writes an event)."""

    kind: str  # "clipped_neighbour" | "erratic_neighbour" | "uncorrelated_neighbour" | "quarantined" | "readmitted"
    neighbour: int
    rounds: int  # rounds in a row that led to it
    factor: float  # the smallest clip factor over its tensors this round (1.0: within bound)


# A tensor of fewer values is judged with the model's other small ones, as one: the distance of a
# 3-value output bias swung 7-21x between a robot's two honest neighbours on lego-5-ring (over
# 3-4 rounds in a row: four honest robots were quarantined), the biases pooled at most 2.1x.
SMALL_TENSOR = 100


def _distances(own: Sequence[Tensor], theirs: Sequence[Tensor], pooled: bool = True) -> list[float]:
    """Per tensor ``||theirs - own||``; ``pooled``: every small tensor's is the small ones' joint distance."""
    d = [float(torch.linalg.vector_norm(t - o)) for o, t in zip(own, theirs)]
    return _pool_small(d, own) if pooled else d


def _whole(a: Sequence[Tensor], b: Sequence[Tensor]) -> float:
    """``||b - a||`` over all tensors."""
    return sum(d * d for d in _distances(a, b, pooled=False)) ** 0.5


def _pool_small(values: list[float], tensors: Sequence[Tensor]) -> list[float]:
    """Norms per tensor -> the same, with each tensor under SMALL_TENSOR values given the small ones' joint norm."""
    small = [i for i, t in enumerate(tensors) if t.numel() < SMALL_TENSOR]
    joint = sum(values[i] ** 2 for i in small) ** 0.5
    return [joint if i in small else v for i, v in enumerate(values)]


def _centred_unit(x: Tensor) -> Tensor | None:
    """x flattened, centred and scaled to unit norm (in float32 without overflow: 1e30s stay
    finite); None when it has no spread to correlate."""
    x = x.detach().flatten().float()
    x = x - x.mean()
    peak = x.abs().max()
    if not torch.isfinite(peak) or peak == 0:
        return None
    x = x / peak
    norm = torch.linalg.vector_norm(x)
    return x / norm if norm > 0 else None


def _unrelated(own: Sequence[Tensor], theirs: Sequence[Tensor], min_z: float) -> bool:
    """Whether most of the tensors large enough to tell correlate with ours by fewer than ``min_z``
    standard errors (a tensor with no spread, a constant, correlates with nothing). Judged whole:
    an honest robot that trained apart for many rounds can hold one tensor (its hash table,
    measured) that has drifted from ours while its decoders still correlate; noise correlates
    nowhere."""
    judged = [i for i, o in enumerate(own) if min_z > 0 and o.numel() >= (2 * min_z) ** 2]
    failed = 0
    for i in judged:
        a, b = _centred_unit(own[i]), _centred_unit(theirs[i])
        r = 0.0 if a is None or b is None else float(a @ b)
        failed += r * own[i].numel() ** 0.5 < min_z
    return bool(judged) and failed * 2 > len(judged)


class NeighbourClipper:
    """One robot's clipping state: the normal disagreement per tensor, streaks, quarantine."""

    def __init__(self, cfg: RobustConfig, num_tensors: int) -> None:
        self.cfg = cfg
        self.num_tensors = num_tensors
        self._normal: deque[list[float]] = deque(maxlen=cfg.window)  # per round, per tensor
        self._tau: list[float] | None = None  # the bound of the last observed round
        self._prev_own: list[Tensor] | None = None
        self.streak: dict[int, int] = {}  # neighbour -> rounds in a row clipped or erratic
        self.reason: dict[int, str] = {}  # neighbour -> "clipped" | "erratic": its last anomaly
        self._seen: dict[int, tuple[int | None, list[Tensor]]] = {}  # at the last observation: round, model
        self.calm: dict[int, int] = {}  # quarantined neighbour -> rounds in a row within the bound
        self.quarantined: set[int] = set()
        self._told: set[int] = set()  # reported in their current streak
        self.factors: dict[int, float] = {}  # last round: neighbour -> smallest clip factor (1.0: not clipped)
        self.clipped_count = 0  # (neighbour, round) pairs clipped so far in this process (benchmarks count them)
        self.erratic_count = 0  # ... and found erratic
        self.uncorrelated_count = 0  # ... and found unrelated to our model

    # --- the bound --------------------------------------------------------------------------
    def _base(self, own: Sequence[Tensor], movement: list[float] | None) -> list[float]:
        """The normal disagreement per tensor before this round's vote: the largest remembered
        over the window; on a cold start, our own movement this round; at least the floor."""
        base = []
        norms = _pool_small([float(torch.linalg.vector_norm(o)) for o in own], own)
        for t in range(len(own)):
            normal = max((n[t] for n in self._normal), default=0.0)
            if not self._normal and movement is not None:  # a cold start: nothing else to go by
                normal = movement[t]
            base.append(max(normal, self.cfg.floor * norms[t]))
        return base

    def _bound(self, base: list[float], votes: list[list[float]], movement: list[float] | None) -> list[float]:
        """tau_t: ``clip_factor`` times the normal (or this round's vote when two or more vote),
        plus twice our own movement this round (what an honest pair may drift apart in it)."""
        if len(votes) >= 2:
            base = [max(b, _lower_median([v[t] for v in votes])) for t, b in enumerate(base)]
        return [self.cfg.clip_factor * b + (2 * movement[t] if movement is not None else 0.0)
                for t, b in enumerate(base)]

    @staticmethod
    def _clip(own: Sequence[Tensor], theirs: Sequence[Tensor], dist: list[float], tau: list[float],
              unrelated: bool, for_dual: bool) -> tuple[list[Tensor], float]:
        """The neighbour's tensors as they enter (the same tensors where within ``tau`` of ours),
        and the smallest clip factor. The anchors take a clipped tensor at ``tau`` from ours (every
        tensor of an unrelated model: ours); the dual takes our own in its place (no
        increment): a clipped pull, integrated round after round, would otherwise grow without
        bound in the dual."""
        out, smallest = [], 1.0
        for o, t, d, bound in zip(own, theirs, dist, tau):
            if d <= bound and not unrelated:
                out.append(t)
                continue
            # d is inf for a model of 1e30s, and an unrelated model carries nothing: factor 0, our own
            factor = 0.0 if unrelated else bound / d if d > 0 else 1.0
            smallest = min(smallest, factor)
            out.append(o.clone() if for_dual or factor == 0 else o + (t - o) * factor)
        return out, smallest

    # --- a round ----------------------------------------------------------------------------
    @torch.no_grad()
    def apply(self, own: Sequence[Tensor], neighbours: Mapping[int, Sequence[Tensor]]) -> dict[int, list[Tensor]]:
        """The neighbours' models as the anchors take them, with the bound of the last observed
        round (the duals saw the same models at its end); quarantined ones left out."""
        if not self.cfg.enabled:
            return {j: list(t) for j, t in neighbours.items()}
        self._prev_own = [o.detach().clone() for o in own]  # theta_i^k: this round's movement is measured from it
        used = {j: t for j, t in neighbours.items() if j not in self.quarantined}
        dist = {j: _distances(own, t) for j, t in used.items()}
        tau = self._tau or self._bound(self._base(own, None), list(dist.values()), None)
        return {j: self._clip(own, t, dist[j], tau, _unrelated(own, t, self.cfg.min_correlation_z), for_dual=False)[0]
                for j, t in used.items()}

    @torch.no_grad()
    def observe(self, own: Sequence[Tensor], neighbours: Mapping[int, Sequence[Tensor]],
                rounds: Mapping[int, int] | None = None) -> tuple[dict[int, list[Tensor]], list[ClipNews]]:
        """The round's new models (theta_j^{k+1}, for the dual update): clipped, the normal
        disagreement, the streaks and the quarantine updated. Returns the models to use (the
        quarantined left out) and the news. ``rounds``: the round of each neighbour's snapshot
        (a model's movement is judged only from one round of it to the next; None: every
        observation is the next round's)."""
        if not self.cfg.enabled:
            return {j: list(t) for j, t in neighbours.items()}, []
        own = [o.detach() for o in own]
        movement = None if self._prev_own is None else _distances(own, self._prev_own)
        dist = {j: _distances(own, t) for j, t in neighbours.items()}
        uncorrelated = {j for j, t in neighbours.items() if _unrelated(own, t, self.cfg.min_correlation_z)}
        votes = [d for j, d in dist.items() if j not in self.quarantined and j not in uncorrelated]
        base = self._base(own, movement)
        tau = self._tau = self._bound(base, votes, movement)
        clipped, self.factors = {}, {}
        for j, theirs in neighbours.items():
            clipped[j], self.factors[j] = self._clip(own, theirs, dist[j], tau, j in uncorrelated, for_dual=True)
            self.clipped_count += self.factors[j] < 1.0 and j not in uncorrelated
        self.uncorrelated_count += len(uncorrelated)
        erratic = self._erratic(neighbours, None if self._prev_own is None else _whole(own, self._prev_own), rounds)
        self.erratic_count += len(erratic)
        self._remember_normal(votes, base, movement)
        news = self._update_streaks(sorted(neighbours), erratic, uncorrelated)
        return {j: t for j, t in clipped.items() if j not in self.quarantined}, news

    def _erratic(self, neighbours: Mapping[int, Sequence[Tensor]], ours: float | None,
                 rounds: Mapping[int, int] | None) -> set[int]:
        """Neighbours whose model moved, from its round heard at the last observation to the
        next, outside ``move_band`` of ``ours``, our own movement in the round (whole models).
        (A snapshot that stands in for a later round again, while we train through a gap, is no
        movement to judge.)"""
        erratic = set()
        for j, theirs in neighbours.items():
            seen = self._seen.get(j)
            now = None if rounds is None else rounds.get(j)
            if seen is None or not ours or (now is not None and seen[0] is not None and now != seen[0] + 1):
                continue
            ratio = _whole(seen[1], theirs) / ours
            if not 1 / self.cfg.move_band <= ratio <= self.cfg.move_band:
                erratic.add(j)
        self._seen = {j: (None if rounds is None else rounds.get(j), [t.detach().clone() for t in theirs])
                      for j, theirs in neighbours.items()}
        return erratic

    def _remember_normal(self, votes: list[list[float]], base: list[float], movement: list[float] | None) -> None:
        """This round's normal, per tensor: the vote (with one neighbour, its distance), but at
        most the normal before it plus twice our own movement this round. Two honest models move
        apart by at most what both moved; so the normal follows honest robots as they learn,
        while a neighbour far outside it cannot raise the bar faster than we move (with one
        neighbour, nothing else would hold it)."""
        if not votes:
            return
        normal = []
        for t, b in enumerate(base):
            vote = _lower_median([v[t] for v in votes])
            normal.append(min(vote, b + 2 * (movement[t] if movement is not None else b)))
        self._normal.append(normal)

    def _update_streaks(self, heard: list[int], erratic: set[int], uncorrelated: set[int]) -> list[ClipNews]:
        news: list[ClipNews] = []
        odd = {j for j in heard if self.factors[j] < 1.0 or j in erratic}  # uncorrelated: factor 0
        within = [j for j in heard if j not in odd and j not in self.quarantined]
        for j in heard:
            factor = self.factors[j]
            if j in odd:
                self.streak[j] = self.streak.get(j, 0) + 1
                self.reason[j] = "uncorrelated" if j in uncorrelated else "clipped" if factor < 1.0 else "erratic"
                self.calm.pop(j, None)
            else:
                self.streak.pop(j, None)
                self.reason.pop(j, None)
                self._told.discard(j)
            run = self.streak.get(j, 0)
            gross = factor < 1 / self.cfg.clip_factor  # further than clip_factor^2 times the normal
            if (run >= self.cfg.report_after or gross) and j not in self._told:
                self._told.add(j)
                news.append(ClipNews(f"{self.reason[j]}_neighbour", j, run, factor))
            if ((run >= self.cfg.report_after or gross) and self.cfg.quarantine and j not in self.quarantined
                    and len(heard) >= 2 and any(k != j for k in within)):
                self.quarantined.add(j)
                news.append(ClipNews("quarantined", j, run, factor))
            elif j in self.quarantined and j not in odd:
                self.calm[j] = self.calm.get(j, 0) + 1
                if self.calm[j] >= self.cfg.readmit_after:
                    self.quarantined.discard(j)
                    self.calm.pop(j, None)
                    news.append(ClipNews("readmitted", j, self.cfg.readmit_after, factor))
        return news

    def forget_own(self) -> None:
        """Our model was replaced (an adoption): the jump is no movement of a round."""
        self._prev_own = None

    # --- persistence --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"normal": [list(n) for n in self._normal], "tau": None if self._tau is None else list(self._tau),
                "streak": dict(self.streak), "reason": dict(self.reason), "calm": dict(self.calm),
                "quarantined": sorted(self.quarantined)}

    def load_state_dict(self, state: dict | None) -> None:
        """From :meth:`state_dict`; None (a checkpoint from before robust consensus): a fresh start."""
        if state is None:
            return
        if any(len(n) != self.num_tensors for n in state["normal"]) or (
                state["tau"] is not None and len(state["tau"]) != self.num_tensors):
            raise ValueError("robust consensus state does not match the model's tensors")
        self._normal = deque((list(map(float, n)) for n in state["normal"]), maxlen=self.cfg.window)
        self._tau = None if state["tau"] is None else [float(x) for x in state["tau"]]
        self.streak = {int(j): int(n) for j, n in state["streak"].items()}
        self.reason = {int(j): str(why) for j, why in state.get("reason", {}).items()}
        self.calm = {int(j): int(n) for j, n in state["calm"].items()}
        self.quarantined = {int(j) for j in state["quarantined"]}


def _lower_median(values: list[float]) -> float:
    ordered = sorted(values)
    return ordered[(len(ordered) - 1) // 2]


@torch.no_grad()
def coordinate_median(models: Sequence[Mapping[str, Tensor]], own: Mapping[str, Tensor] | None = None
                      ) -> dict[str, Tensor]:
    """Per coordinate, the median of the models; with an even number of them, ``own`` votes too
    (when given; else the mean of the two middle values). One model: itself."""
    if not models:
        raise ValueError("no model to take the median of")
    voters = list(models) + ([own] if own is not None and len(models) % 2 == 0 else [])
    out = {}
    for name in models[0]:
        stack = torch.stack([m[name].float() for m in voters])
        if len(voters) % 2:
            out[name] = stack.median(dim=0).values
        else:
            ordered = stack.sort(dim=0).values
            mid = len(voters) // 2
            out[name] = (ordered[mid - 1] + ordered[mid]) / 2
    return out
