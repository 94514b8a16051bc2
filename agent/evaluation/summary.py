"""A scored run in a few numbers: the robots' final scores, and how far they are from the baselines.

The gain over "alone" is taken on the views only *other* robots saw: what a robot learnt from
its neighbours, which it cannot have learnt by itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from agent.evaluation.baselines import AloneScores, Baselines
from agent.evaluation.run import RunScores
from agent.metrics import finite_mean

__all__ = ["RunSummary", "BaselineGaps", "summarise"]


@dataclass
class BaselineGaps:
    centralised_psnr: float | None
    gap_to_centralised_db: float | None  # centralised - swarm mean; None: no robot scored
    gain_over_alone_others_only_db: dict[int, float] | None  # swarm - alone per robot with both; None: no "alone"

    def to_dict(self) -> dict:
        doc = {"centralised_psnr": self.centralised_psnr}
        if self.gap_to_centralised_db is not None:
            doc["gap_to_centralised_db"] = self.gap_to_centralised_db
        if self.gain_over_alone_others_only_db is not None:
            gains = self.gain_over_alone_others_only_db
            doc["gain_over_alone_others_only_db"] = {str(i): g for i, g in gains.items()}
            doc["min_gain_over_alone_others_only_db"] = min(gains.values()) if gains else None
        return doc


@dataclass
class RunSummary:
    mean_psnr: float | None  # over the robots' final snapshots
    mean_psnr_others_only: float | None
    max_rotation_error_deg: float | None  # a robot without a score counts as 0
    max_translation_error: float | None
    baselines: BaselineGaps | None = None

    def to_dict(self) -> dict:
        doc = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "baselines"}
        return {**doc, **(self.baselines.to_dict() if self.baselines else {})}


def summarise(scores: RunScores, baselines: Baselines | None = None) -> RunSummary:
    finals = {i: scores.final(i) for i in scores.rounds}
    scored = [f for f in finals.values() if f is not None]
    s = RunSummary(
        mean_psnr=finite_mean(f.psnr for f in scored),
        mean_psnr_others_only=finite_mean(f.psnr_others_only for f in scored),
        max_rotation_error_deg=max(((f and f.rotation_error_deg) or 0.0 for f in finals.values()), default=None),
        max_translation_error=max(((f and f.translation_error) or 0.0 for f in finals.values()), default=None),
    )
    if baselines is not None:
        c = baselines.centralised.psnr
        gains = None
        if baselines.alone is not None:
            alone = {i: a.psnr_others_only for i, a in baselines.alone.items() if isinstance(a, AloneScores)}
            gains = {i: f.psnr_others_only - alone[i] for i, f in finals.items()
                    if f is not None and _number(f.psnr_others_only) and _number(alone.get(i))}
        s.baselines = BaselineGaps(c, c - s.mean_psnr if s.mean_psnr is not None else None, gains)
    return s


def _number(x: float | None) -> bool:
    return x is not None and not math.isnan(x)
