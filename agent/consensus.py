"""Consensus ADMM (C-ADMM) in DiNNO's form, over the parameters of any torch module.

One robot i in round k minimises, for B optimiser steps,

    L_i(theta) + <theta, y_i> + rho_k * sum_{j in N_i} || theta - (theta_i^k + theta_j^k) / 2 ||^2

then publishes theta_i^{k+1}, receives theta_j^{k+1} from the neighbours that answered, and
updates its dual ``y_i += rho_k * sum_j (theta_i^{k+1} - theta_j^{k+1})`` over those only.

The penalty is applied as an explicit gradient added after ``backward()`` (no autograd graph
over millions of parameters): ``d/dtheta = y_i + 2 rho_k (n theta - sum_j a_j)`` with the
anchors ``a_j = (theta_i^k + theta_j^k) / 2``. Nothing here knows about NeRF or the network.

Every theta_j passes through :class:`agent.robust.NeighbourClipper` first (robust consensus: a
neighbour's model enters only within the swarm's normal disagreement of the robot's own).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import torch
from torch import Tensor

from agent.robust import ClipNews, NeighbourClipper, RobustConfig


@dataclass
class ConsensusConfig:
    """rho against the scale of the data term. The RGB loss is a *mean* over rays, so one hash
    entry's data gradient is ~1e-5; a penalty gradient 2 rho (theta - a) above that pins every
    robot to the round's anchors and learning stops (docs/results.md). With
    rho ~ 1e-5 the data term leads where a robot has data, and entries it never sees still
    follow its neighbours (Adam's steps do not depend on the gradient's scale). The best value
    depends on the scene and field (the quickstart's is 3e-6): sweep it, as docs/results.md does.
    """

    rho0: float = 1e-5
    rho_growth: float = 1.0  # rho_k = rho0 * rho_growth**k  (DiNNO grows it slowly)
    rho_max: float = 1.0
    # rho of the dense MLP weights against the hash table's: every ray's gradient reaches an MLP
    # weight, only a few a hash entry, so one rho that lets the table follow its data leaves the
    # decoders free to drift apart, and a neighbour's entries are then decoded by a different MLP.
    mlp_rho_scale: float = 1.0
    forget_edge_after: int = 2  # an edge silent for this many rounds restarts its dual at zero
    # (a cut link, a dead neighbour): the old y_ij priced a disagreement both models have since
    # left behind, and applied on return it pushes in a stale direction. 0 = never forget.
    robust: RobustConfig = field(default_factory=RobustConfig)  # clipping of neighbours' models (agent.robust)

    def __post_init__(self) -> None:
        if self.rho0 <= 0 or self.rho_growth < 1.0 or self.rho_max < self.rho0:
            raise ValueError("need rho0 > 0, rho_growth >= 1 and rho_max >= rho0")
        if self.mlp_rho_scale <= 0:
            raise ValueError("mlp_rho_scale must be > 0")
        if self.forget_edge_after < 0:
            raise ValueError("forget_edge_after must be >= 0 (0 = never)")

    def rho(self, round_index: int) -> float:
        return min(self.rho0 * self.rho_growth**round_index, self.rho_max)


class Consensus:
    """The C-ADMM state of one robot: duals, the current round's anchors and rho."""

    def __init__(self, params: Sequence[Tensor], cfg: ConsensusConfig, rho_scales: Sequence[float] | None = None) -> None:
        """rho_scales: per parameter, a factor on rho (None: 1 for all)."""
        self.cfg = cfg
        self.rho_scales = list(rho_scales) if rho_scales is not None else [1.0] * len(params)
        if len(self.rho_scales) != len(params):
            raise ValueError(f"{len(self.rho_scales)} rho scales for {len(params)} parameters")
        self._zeros = [torch.zeros_like(p, memory_format=torch.contiguous_format) for p in params]
        self.edge_duals: dict[int, list[Tensor]] = {}  # y_ij, per neighbour j ever heard
        self.edge_round: dict[int, int] = {}  # round of y_ij's last update
        self.duals = [z.clone() for z in self._zeros]  # sum of y_ij over the neighbours heard this round
        self.anchor_sum: list[Tensor] | None = None  # sum_j (theta_i^k + theta_j^k) / 2
        self.num_neighbours = 0
        self.rho = cfg.rho(0)
        self.round = 0
        self.clipper = NeighbourClipper(cfg.robust, len(params))
        self.news: list[ClipNews] = []  # what the last dual update found about the neighbours

    # --- one round -------------------------------------------------------------------------
    @torch.no_grad()
    def begin_round(self, round_index: int, own: Sequence[Tensor], neighbours: Mapping[int, Sequence[Tensor]]) -> None:
        """Fix the anchors of round k from theta_i^k and the theta_j^k of the neighbours heard
        (clipped as the dual update at the end of round k - 1 clipped them; quarantined left out)."""
        neighbours = self.clipper.apply(own, neighbours)
        self.round = round_index
        self.rho = self.cfg.rho(round_index)
        self.num_neighbours = len(neighbours)
        self.duals = [z.clone() for z in self._zeros]
        for j in neighbours:
            self._forget_if_silent(j, round_index)
            for y, y_ij in zip(self.duals, self.edge_duals.get(j, ())):
                y.add_(y_ij)
        if not neighbours:
            self.anchor_sum = None
            return
        sums = [o.detach().clone().mul_(0.5 * self.num_neighbours) for o in own]
        for theta_j in neighbours.values():
            for s, t in zip(sums, theta_j):
                s.add_(t, alpha=0.5)
        self.anchor_sum = sums

    def _forget_if_silent(self, j: int, round_index: int) -> None:
        """Drop y_ij if the edge missed ``forget_edge_after`` rounds or more. Both ends missed
        the same rounds, so both drop it and the pair of duals stays antisymmetric."""
        last = self.edge_round.get(j)
        limit = self.cfg.forget_edge_after
        if limit and last is not None and round_index - last - 1 >= limit:
            self.edge_duals.pop(j, None)
            self.edge_round.pop(j, None)

    @torch.no_grad()
    def add_penalty_grad(self, params: Sequence[Tensor]) -> None:
        """Add the gradient of ``<theta, y> + rho sum_j ||theta - a_j||^2`` to ``p.grad``."""
        for i, p in enumerate(params):
            g = self.duals[i].clone()
            if self.anchor_sum is not None:
                g.add_(p.detach() * self.num_neighbours - self.anchor_sum[i], alpha=2 * self.rho * self.rho_scales[i])
            if p.grad is None:
                p.grad = g
            else:
                p.grad.add_(g)

    @torch.no_grad()
    def penalty(self, params: Sequence[Tensor]) -> float:
        """Value of the consensus terms (for logs): ``<theta, y> + rho sum_j ||theta - a_j||^2``.

        Uses ``sum_j ||x - a_j||^2 = n ||x||^2 - 2 <x, sum_j a_j> + sum_j ||a_j||^2``; the last
        term is constant within a round and left out, so only changes of this value are meaningful.
        """
        total = 0.0
        for i, p in enumerate(params):
            x = p.detach()
            total += float((x * self.duals[i]).sum())
            if self.anchor_sum is not None:
                total += self.rho * self.rho_scales[i] * float(self.num_neighbours * (x * x).sum() - 2 * (x * self.anchor_sum[i]).sum())
        return total

    @torch.no_grad()
    def dual_update(self, own: Sequence[Tensor], neighbours: Mapping[int, Sequence[Tensor]],
                    rounds: Mapping[int, int] | None = None) -> None:
        """``y_ij += rho_k (theta_i^{k+1} - theta_j^{k+1})`` for the neighbours heard (the next
        round's ``begin_round`` sums them), each theta_j clipped first; a neighbour quarantined
        now loses its edge dual. ``rounds``: each snapshot's round (NeighbourClipper.observe)."""
        neighbours, self.news = self.clipper.observe(own, neighbours, rounds)
        for news in self.news:
            if news.kind == "quarantined":
                self.edge_duals.pop(news.neighbour, None)
                self.edge_round.pop(news.neighbour, None)
        for j, theta_j in neighbours.items():
            self._forget_if_silent(j, self.round)  # a returning edge is usually seen here first
            edge = self.edge_duals.setdefault(j, [z.clone() for z in self._zeros])
            self.edge_round[j] = self.round
            for y, o, t, scale in zip(edge, own, theta_j, self.rho_scales):
                y.add_(o.detach() - t, alpha=self.rho * scale)

    @torch.no_grad()
    def reset_duals(self) -> None:
        """Forget the accumulated disagreement (theta_i was replaced: the old duals priced a model
        that is gone)."""
        self.edge_duals.clear()
        self.edge_round.clear()
        self.clipper.forget_own()
        for y in self.duals:
            y.zero_()

    # --- persistence ---------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"edge_duals": {j: [d.clone() for d in y] for j, y in self.edge_duals.items()},
                "edge_round": dict(self.edge_round), "rho": self.rho, "round": self.round,
                "robust": self.clipper.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if "edge_duals" not in state:
            raise ValueError("consensus state from an older dinerf (one summed dual, not one per neighbour)")
        edges = state["edge_duals"]
        for y in edges.values():
            if len(y) != len(self._zeros) or any(a.shape != b.shape for a, b in zip(y, self._zeros)):
                raise ValueError("consensus state does not match the model's parameter shapes")
        self.edge_duals = {int(j): [d.to(z.device, copy=True) for d, z in zip(y, self._zeros)]
                           for j, y in edges.items()}
        # A checkpoint from before edge_round: every edge counts as updated in its round.
        self.edge_round = {int(j): int(r) for j, r in state.get("edge_round", {j: state["round"] for j in edges}).items()}
        self.duals = [z.clone() for z in self._zeros]
        self.rho = float(state["rho"])
        self.round = int(state["round"])
        self.anchor_sum = None
        self.num_neighbours = 0
        self.clipper.load_state_dict(state.get("robust"))


def disagreement(thetas: Sequence[Sequence[Tensor]]) -> list[float]:
    """Per robot ``||theta_i - mean|| / ||mean||`` over all parameters (a consensus metric)."""
    count = len(thetas)
    mean = [sum(t[i] for t in thetas) / count for i in range(len(thetas[0]))]
    mean_norm = sum(float((m * m).sum()) for m in mean) ** 0.5
    out = []
    for t in thetas:
        d = sum(float(((a - m) ** 2).sum()) for a, m in zip(t, mean)) ** 0.5
        out.append(d / max(mean_norm, 1e-30))
    return out
