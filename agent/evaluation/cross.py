"""Scores without ground truth: every robot's field on every robot's own held-out frames.

Robots of one's own have no truth and no test views that no robot saw. What they do have: each
keeps every k-th of its own frames out of training (``training.own_holdout_every``). Robot i's
field renders robot j's held-out frames through j's *estimated* pose (j's local frame -> the
shared frame): if the maps agree and the poses are right, i scores on j's frames about as j does
on its own; a wrong pose or a map that does not hold j's part of the scene shows as a low cell.
Beside the scores, each robot's relative pose as found, how sure the coarse step was of it
(the rotation's 1-sigma), and its alignment state, from its run folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from agent.data.views import Views
from agent.geometry import pose_summary, transform_c2w
from agent.metrics import finite_mean
from agent.telemetry import read_events, read_telemetry
from agent.trainer import RobotTrainer

__all__ = ["CrossScores", "RobotFrame", "score_cross", "robot_frame"]


@dataclass
class RobotFrame:
    """Where a robot's frame was placed in the shared one, and how it got there."""

    pose: list[list[float]]  # [4, 4] T_shared_from_local, estimated
    rotation_deg: float
    translation: float  # |t|, shared-frame units
    scale: float
    alignment: str  # reference | coarse | identity | unaligned | pending (its last round's)
    rotation_sigma_deg: float | None  # the coarse step's 1-sigma (None: no estimate)
    via: int | None  # the neighbour it was aligned through
    inliers: int | None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class CrossScores:
    """``psnr[i][j]``: robot i's field on robot j's held-out frames (mean over them)."""

    psnr: dict[int, dict[int, float]] = field(default_factory=dict)
    ssim: dict[int, dict[int, float]] = field(default_factory=dict)
    frames: dict[int, int] = field(default_factory=dict)  # robot j -> held-out frames scored
    robots: dict[int, RobotFrame] = field(default_factory=dict)

    def own(self, i: int) -> float:
        return self.psnr[i][i]

    def others(self, i: int) -> float:
        """Robot i's field on the other robots' frames: what the swarm taught it."""
        return finite_mean([v for j, v in self.psnr[i].items() if j != i])

    def to_dict(self) -> dict:
        return {"psnr": {str(i): {str(j): v for j, v in row.items()} for i, row in self.psnr.items()},
                "ssim": {str(i): {str(j): v for j, v in row.items()} for i, row in self.ssim.items()},
                "frames": {str(j): n for j, n in self.frames.items()},
                "robots": {str(i): r.to_dict() for i, r in self.robots.items()},
                "mean_others": {str(i): self.others(i) for i in self.psnr}}


def robot_frame(trainer: RobotTrainer, run_dir) -> RobotFrame:
    """The robot's estimated pose and, from its run folder, its alignment state and the coarse step's sigma."""
    from pathlib import Path

    from agent.checkpoint import EVENTS, TELEMETRY

    with torch.no_grad():
        matrix = trainer.pose.matrix().detach().double().cpu()
    summary = pose_summary(matrix)
    records = read_telemetry(Path(run_dir) / TELEMETRY)
    aligned = [e for e in read_events(Path(run_dir) / EVENTS) if e.get("event") == "aligned"]
    last = aligned[-1] if aligned else {}
    return RobotFrame(pose=matrix.tolist(), rotation_deg=summary["rotation_deg"], translation=math.hypot(*summary["translation"]),
                      scale=summary["scale"], alignment=records[-1].alignment if records else "unknown",
                      rotation_sigma_deg=last.get("rotation_sigma_deg"), via=last.get("via"),
                      inliers=last.get("inliers"))


@torch.no_grad()
def score_cross(trainers: dict[int, RobotTrainer], holdouts: dict[int, Views | None], with_ssim: bool = True,
                run_dirs: dict | None = None) -> CrossScores:
    """Every robot's field on every robot's held-out frames (local frame -> shared through that robot's pose)."""
    out = CrossScores()
    shared: dict[int, Views] = {}
    for j, views in holdouts.items():
        if views is None or not len(views):
            continue
        pose_j = trainers[j].pose.matrix().detach().cpu().to(views.c2w.dtype)
        shared[j] = Views(views.images, transform_c2w(pose_j, views.c2w), views.intrinsics, views.names, None,
                          views.meta)
        out.frames[j] = len(views)
    for i, trainer in trainers.items():
        out.psnr[i], out.ssim[i] = {}, {}
        for j, views in shared.items():
            scores = trainer.evaluate(views, frame="shared", with_ssim=with_ssim)
            out.psnr[i][j] = finite_mean(scores["psnr"])
            if with_ssim:
                out.ssim[i][j] = finite_mean(scores["ssim"])
        if run_dirs is not None:
            out.robots[i] = robot_frame(trainer, run_dirs[i])
    return out
