"""The split itself: robots, held-out views and the truth, in memory (:func:`split_views`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from agent.data.capture import estimate_scene_box
from agent.data.split.assign import assign, overlaps
from agent.data.split.config import SplitConfig
from agent.data.split.frames import depth_prior, local_frame
from agent.data.views import DataError, Views
from agent.geometry import box_from_center, sim3_decompose, sim3_inverse, transform_c2w

__all__ = ["RobotSplit", "SplitResult", "split_views", "split_dataset", "test_indices"]


@dataclass
class RobotSplit:
    id: int
    views: Views  # in the robot's local frame; depth = the depth prior (or None)
    indices: list[int]  # into the source views
    T_world_from_local: Tensor  # [4, 4] float64
    sector_deg: tuple[float, float]  # widened sector [start, end) in degrees; trajectory: its views' [start, end]
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
    seen_by: list[list[int]]  # per eval view: the robots that saw its part of the scene
    reference_id: int
    center: Tensor  # [3] scene centre used for the sectors
    up: Tensor  # [3] unit up axis
    azimuth_deg: Tensor  # [M] of every source view
    margin_deg: float  # sectors: delta
    mean_overlap: float
    box_center_world: Tensor  # [3]
    box_half_size: float
    box_source: str
    source: str = ""
    notes: list[str] = field(default_factory=list)
    layout: str = "circle"  # circle | arc (sectors) | trajectory (segments), see agent.data.split
    margin_views: int = 0  # trajectory: views shared at each border between segments

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
    if len(train_idx) < len(ids):
        raise DataError(f"robot {ids[len(train_idx)]} gets no views: {len(train_idx)} training views for "
                        f"{len(ids)} robots; use fewer robots")
    got = assign(views, cfg, train_idx, eval_idx, len(ids))
    achieved = overlaps(got.train)
    for k, rid in enumerate(ids):
        if not got.train[:, k].any():
            a, b = got.ranges_deg[k]
            raise DataError(f"robot {rid} gets no views (sector {a:.0f}-{b:.0f} deg is empty); use fewer robots")

    gen = torch.Generator().manual_seed(cfg.seed)
    reference = ids[0]
    robots: dict[int, RobotSplit] = {}
    for k, rid in enumerate(ids):
        idx = [train_idx[j] for j in np.nonzero(got.train[:, k])[0]]
        robots[rid] = _robot_split(views, cfg, rid, rid == reference, idx, gen, got.ranges_deg[k], float(achieved[k]))
    box_c, box_h, box_src = estimate_scene_box(views)
    notes = list(got.notes)
    if box_src != "dataset":
        notes.append(f"scene box estimated from the {box_src}: centre {box_c.tolist()}, half-size {box_h:.3f}")
    return SplitResult(
        config=cfg,
        robots=robots,
        eval_views=views.subset(eval_idx),
        eval_indices=eval_idx,
        seen_by=[[ids[k] for k in np.nonzero(row)[0]] for row in got.test],
        reference_id=reference,
        center=got.center,
        up=got.up,
        azimuth_deg=got.azimuth_deg,
        margin_deg=got.margin_deg,
        mean_overlap=float(np.mean(achieved)),
        box_center_world=box_c,
        box_half_size=box_h,
        box_source=box_src,
        source=str(views.meta.get("source", "")),
        notes=notes,
        layout=got.layout,
        margin_views=got.margin_views,
    )


def split_dataset(source: str | Path, cfg: SplitConfig, width: int | None = None) -> tuple[Views, SplitResult]:
    """Load ``source`` and split it: (the views as split, the split), for the CLI and the scenarios.

    The robots' images are ``cfg.robot_image_width`` wide when it is set (robot folders, their
    intrinsics and depth all consistent), else ``width``; the held-out views are then downscaled
    to ``width``, the resolution of the evaluation. The split itself (sectors, held-out views,
    box) depends on the poses only, not on the width.
    """
    from agent.data.images import resize_views
    from agent.data.loaders import load_views

    views = load_views(source, width=cfg.robot_image_width or width)
    result = split_views(views, cfg)
    if cfg.robot_image_width is not None and width is not None and result.eval_indices:
        result.eval_views = resize_views(result.eval_views, width)
    return views, result


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


