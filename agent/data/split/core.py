"""The split itself: robots, held-out views and the truth, in memory (:func:`split_views`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from agent.data.capture import estimate_scene_box
from agent.data.split.assign import membership, overlaps, sectors
from agent.data.split.config import SplitConfig
from agent.data.split.frames import depth_prior, local_frame
from agent.data.views import DataError, Views
from agent.geometry import box_from_center, sim3_decompose, sim3_inverse, transform_c2w

__all__ = ["RobotSplit", "SplitResult", "split_views", "test_indices"]


@dataclass
class RobotSplit:
    id: int
    views: Views  # in the robot's local frame; depth = the depth prior (or None)
    indices: list[int]  # into the source views
    T_world_from_local: Tensor  # [4, 4] float64
    sector_deg: tuple[float, float]  # widened sector [start, end) in degrees
    overlap: float  # achieved: fraction of this robot's views also held by another robot
    depth_affine: Tensor | None = None  # [M_i, 2] (a_m, b_m): prior = a_m * true_local_depth + b_m

    @property
    def cameras_world(self) -> Tensor:
        """The true world camera-to-world of this robot's views.  -> [M_i, 4, 4] float64.

        For robots with images only, the evaluation aligns each robot's own SfM cameras to these.
        """
        return transform_c2w(self.T_world_from_local, self.views.c2w.to(torch.float64))


@dataclass
class SplitResult:
    config: SplitConfig
    robots: dict[int, RobotSplit]
    eval_views: Views  # world frame, true depth if the source has depth
    eval_indices: list[int]
    seen_by: list[list[int]]  # per eval view
    reference_id: int
    center: Tensor  # [3] scene centre used for the sectors
    up: Tensor  # [3] unit up axis
    azimuth_deg: Tensor  # [M] of every source view
    margin_deg: float  # delta
    mean_overlap: float
    box_center_world: Tensor  # [3]
    box_half_size: float
    box_source: str
    source: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def T_shared_from_local(self) -> dict[int, Tensor]:
        """What robot i's relative pose T_i should converge to: inv(T_ref) T_i.  {id: [4, 4]}."""
        ref_inv = sim3_inverse(self.robots[self.reference_id].T_world_from_local)
        return {i: ref_inv @ r.T_world_from_local for i, r in self.robots.items()}

    @property
    def box_from_world(self) -> Tensor:
        """[4, 4]: world -> normalised box coordinates, ``(x - centre) / half_size``."""
        return box_from_center(self.box_center_world, self.box_half_size)

    @property
    def box_from_shared(self) -> Tensor:
        """[4, 4]: shared frame g (the reference's local frame) -> box coordinates [-1, 1]^3."""
        return self.box_from_world @ self.robots[self.reference_id].T_world_from_local



def split_views(views: Views, cfg: SplitConfig | None = None) -> SplitResult:
    """Split ``views`` (world frame) into robots, held-out views and the truth; nothing is written."""
    cfg = cfg or SplitConfig()
    ids = cfg.robot_ids
    if cfg.depth_prior != "none" and views.depth is None:
        raise DataError(
            f"depth prior {cfg.depth_prior!r} needs a source with depth (procedural, nerfstudio depth maps "
            f"or a COLMAP model); {views.meta.get('source', 'this source')} has none"
        )
    eval_idx, train_idx = _holdout(len(views), cfg)
    sec = sectors(views, cfg, train_idx, len(ids))
    mem_train = membership(sec.azimuth_deg.numpy()[train_idx], sec.starts, sec.width, sec.margin)  # [M_train, N]
    achieved = overlaps(mem_train)
    for k, rid in enumerate(ids):
        if not mem_train[:, k].any():
            raise DataError(f"robot {rid} gets no views (sector {sec.starts[k]:.0f}-{sec.starts[k] + sec.width:.0f} deg "
                            "is empty); use fewer robots")

    gen = torch.Generator().manual_seed(cfg.seed)
    reference = ids[0]
    robots: dict[int, RobotSplit] = {}
    for k, rid in enumerate(ids):
        idx = [train_idx[j] for j in np.nonzero(mem_train[:, k])[0]]
        sector = (float(sec.starts[k] - sec.margin), float(sec.starts[k] + sec.width + sec.margin))
        robots[rid] = _robot_split(views, cfg, rid, rid == reference, idx, gen, sector, float(achieved[k]))

    seen_by = []
    if eval_idx:
        mem_eval = membership(sec.azimuth_deg.numpy()[eval_idx], sec.starts, sec.width, sec.margin)
        seen_by = [[ids[k] for k in np.nonzero(row)[0]] for row in mem_eval]
    box_c, box_h, box_src = estimate_scene_box(views)
    notes: list[str] = []
    if box_src != "dataset":
        notes.append(f"scene box estimated from the {box_src}: centre {box_c.tolist()}, half-size {box_h:.3f}")
    return SplitResult(
        config=cfg,
        robots=robots,
        eval_views=views.subset(eval_idx),
        eval_indices=eval_idx,
        seen_by=seen_by,
        reference_id=reference,
        center=sec.center,
        up=sec.up,
        azimuth_deg=sec.azimuth_deg,
        margin_deg=sec.margin,
        mean_overlap=float(np.mean(achieved)),
        box_center_world=box_c,
        box_half_size=box_h,
        box_source=box_src,
        source=str(views.meta.get("source", "")),
        notes=notes,
    )


def test_indices(count: int, every: int) -> list[int]:
    """The test views of a dataset of ``count`` views: 0, k, 2k, ... (none when ``every`` is 0).

    The one rule for views held out from every robot (the split) and from the centralised
    baseline, so that both are scored on the same views."""
    return list(range(0, count, every)) if every > 0 else []


def _holdout(m: int, cfg: SplitConfig) -> tuple[list[int], list[int]]:
    """(test view indices, training view indices) of ``m`` source views."""
    eval_idx = test_indices(m, cfg.test_every)
    held = set(eval_idx)
    train_idx = [i for i in range(m) if i not in held]
    if not train_idx:
        raise DataError(f"no training views left: {m} views with test_every={cfg.test_every}")
    return eval_idx, train_idx



def _robot_split(views: Views, cfg: SplitConfig, rid: int, is_reference: bool, idx: list[int], gen: torch.Generator,
                 sector: tuple[float, float], overlap: float) -> RobotSplit:
    """Robot ``rid``'s views ``idx`` moved into its local frame, with its depth prior."""
    sub = views.subset(idx)
    t_wl = local_frame(cfg, is_reference, sub, gen)
    scale = float(sim3_decompose(t_wl)[0])
    c2w_local = transform_c2w(sim3_inverse(t_wl), sub.c2w.to(torch.float64)).float()
    depth, affine = depth_prior(cfg, sub, scale, gen) if cfg.depth_prior != "none" else (None, None)
    meta = {k2: v for k2, v in sub.meta.items() if k2 not in ("scene_box_world",)}
    meta.update(robot_id=rid, frame=cfg.frame, depth_prior=cfg.depth_prior)
    local = Views(sub.images, c2w_local, sub.intrinsics.clone(), list(sub.names), depth, meta)
    return RobotSplit(rid, local, idx, t_wl, sector, overlap, affine)


