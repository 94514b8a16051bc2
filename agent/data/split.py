"""Turn one posed dataset into N robots the way the Di-NeRF paper does, plus the evaluation truth.

Each robot gets the views of one sector of directions around the scene centre, re-expressed in
its own local frame; held-out views of the whole scene (in the world frame) are kept for
evaluation; the true relative poses go to a file that only evaluation reads.

Sectors. The azimuth of a camera is the angle of its centre about the up axis through the
scene centre (up: given, or the mean camera up vector; centre: given, or the least-squares
point closest to all optical axes). Robot k (k = 0..N-1, in id order) owns the core sector
``[start + k w, start + (k + 1) w)`` with ``w = 360 / N``; every sector is widened by a margin
``delta`` on both sides, so robot k holds the training views whose azimuth falls in
``[start + k w - delta, start + (k + 1) w + delta)``.

Overlap, precisely: the overlap of robot i is the fraction of robot i's training views that
also belong to at least one other robot. For azimuths spread uniformly it is
``4 delta / (w + 2 delta)``; rather than trust that, ``delta`` is chosen on the actual views
(among all values at which a view enters a neighbour's sector, below ``w / 2``) so that the mean
over robots of the achieved overlap is closest to the requested one. The achieved per-robot and
mean overlaps are reported.

Held-out views: every k-th view of the source order (indices 0, k, 2k, ...) is used by nobody
for training. Each carries ``seen_by``: the robots whose widened sector contains its direction,
so "views only other robots saw" for robot i are the held-out views whose ``seen_by`` excludes i.

Local frames (``T_world_from_local`` maps a robot's local coordinates into the world):
``first_camera`` (the paper's: the robot's first camera is its origin), ``offset`` (the reference
keeps the world frame; every other robot is offset by a fixed rotation and translation),
``world`` (identity: known poses), ``random`` (seeded rotation, translation and optional scale).
Poses become ``transform_c2w(sim3_inverse(T), c2w)``; depths are divided by the scale.
The shared frame g of the swarm is the local frame of the reference robot (the lowest id).

Images only (``images_only``): robot folders get no poses, so each robot's local frame will be
its own SfM's (arbitrary rotation, translation and scale), unknown at split time. ``scene.json``
then has no box (the reference derives it from its SfM), and ``truth.json`` gives, instead of
``T_world_from_local``, the true world cameras of each robot's views (``cameras_world``), to which
the evaluation aligns the robot's SfM cameras (``agent.evaluation.calibrate_frame``).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from agent.data.capture import azimuths_deg, estimate_scene_box, mean_up, scene_center
from agent.data.folder import matrix_to_list, write_json, write_views_folder
from agent.data.views import DataError, Views
from agent.geometry import (
    box_from_center,
    random_rotation,
    sim3_decompose,
    sim3_inverse,
    so3_exp,
    transform_c2w,
)

__all__ = [
    "SplitConfig",
    "RobotSplit",
    "SplitResult",
    "split_views",
    "test_indices",
    "write_split",
    "robot_folder",
    "estimate_scene_box",
    "scene_center",
    "mean_up",
    "azimuths_deg",
    "offset_transform",
]

FrameKind = Literal["first_camera", "offset", "world", "random"]
DepthPrior = Literal["none", "true", "scaled"]


@dataclass
class SplitConfig:
    """How to split a dataset into robots (see the module docstring for the exact definitions)."""

    robots: int = 2
    ids: list[int] | None = None  # robot ids, default 1..robots; the reference is the lowest
    overlap: float = 0.0  # requested mean fraction of a robot's views shared with a neighbour, [0, 0.4]
    test_every: int = 8  # every k-th view (0, k, 2k, ...) is a test view, seen by no robot; 0 = none
    frame: FrameKind = "first_camera"
    offset_rotation_deg: tuple[float, float, float] = (30.0, 30.0, 30.0)  # about x, then y, then z
    offset_translation: tuple[float, float, float] = (3.0, 3.0, 3.0)
    random_max_angle_deg: float = 180.0
    random_max_translation: float = 3.0  # uniform in the ball of this radius
    random_max_scale: float = 1.0  # > 1: Sim(3), scale log-uniform in [1/x, x]; 1: SE(3)
    depth_prior: DepthPrior = "none"
    depth_scale_range: tuple[float, float] = (0.5, 2.0)  # a_m of the "scaled" prior
    depth_shift_range: tuple[float, float] = (-0.5, 0.5)  # b_m of the "scaled" prior
    up: tuple[float, float, float] | None = None
    center: tuple[float, float, float] | None = None
    sector_start_deg: float = 0.0
    images_only: bool = False  # robot folders without poses (robots must run their own SfM)
    calibrated_cameras: bool = False  # images_only: each robot folder also gets its camera's focal length
    # Robot folders get their images at this width (e.g. for their own SfM, which needs more
    # pixels than training); None: the dataset's width as loaded. Test views keep that width.
    robot_image_width: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise DataError(f"robots must be >= 1, got {self.robots}")
        if self.ids is not None:
            if len(self.ids) != self.robots or len(set(self.ids)) != len(self.ids) or min(self.ids) < 0:
                raise DataError(f"ids must be {self.robots} distinct non-negative integers, got {self.ids}")
        if not 0.0 <= self.overlap <= 0.4:
            raise DataError(f"overlap must be in [0, 0.4], got {self.overlap}")
        if self.test_every < 0 or self.test_every == 1:
            raise DataError(f"test_every must be 0 (none) or >= 2, got {self.test_every}")
        for name, allowed in (("frame", FrameKind), ("depth_prior", DepthPrior)):
            if getattr(self, name) not in allowed.__args__:
                raise DataError(f"{name} must be one of {list(allowed.__args__)}, got {getattr(self, name)!r}")
        if self.random_max_scale < 1.0:
            raise DataError(f"random_max_scale must be >= 1, got {self.random_max_scale}")
        if self.calibrated_cameras and not self.images_only:
            raise DataError("calibrated_cameras is for images_only robots (robots with poses have their intrinsics)")
        if self.robot_image_width is not None and self.robot_image_width < 8:
            raise DataError(f"robot_image_width must be >= 8 pixels, got {self.robot_image_width}")
        if self.images_only and self.depth_prior != "none":
            raise DataError("images_only robots have no transforms.json to carry a depth prior; use depth_prior='none'")

    @property
    def robot_ids(self) -> list[int]:
        return sorted(self.ids) if self.ids is not None else list(range(1, self.robots + 1))


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


# --------------------------------------------------------------------------------------------
# Sectors
# --------------------------------------------------------------------------------------------


def _membership(az: np.ndarray, starts: np.ndarray, width: float, delta: float) -> np.ndarray:
    """[M, N] bool: azimuth in sector k widened by delta on both sides."""
    rel = (az[:, None] - starts[None, :] + delta) % 360.0
    return rel < width + 2 * delta


def _overlaps(mem: np.ndarray) -> np.ndarray:
    """[N] fraction of each robot's views that another robot also holds (nan for an empty robot)."""
    shared = mem.sum(1) > 1
    count = mem.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (mem & shared[:, None]).sum(0) / count, np.nan)


def _choose_margin(az: np.ndarray, starts: np.ndarray, width: float, target: float) -> float:
    """The margin delta in [0, w/2) whose mean achieved overlap is closest to ``target``."""
    if len(starts) < 2 or target <= 0.0:
        return 0.0
    # membership only changes where a view crosses a sector boundary: try just past each crossing
    dist = np.abs(((az[:, None] - starts[None, :] + 180.0) % 360.0) - 180.0).ravel()
    cands = np.unique(np.concatenate([[0.0], dist + 1e-6]))
    cands = cands[cands < width / 2]
    best, best_err = 0.0, math.inf
    for delta in cands:
        err = abs(float(np.nanmean(_overlaps(_membership(az, starts, width, delta)))) - target)
        if err < best_err - 1e-12:
            best, best_err = float(delta), err
    return best


def offset_transform(rotation_deg: tuple[float, float, float], translation: tuple[float, float, float]) -> Tensor:
    """``[R | t]`` with R = Rz(c) Ry(b) Rx(a) for rotation_deg = (a, b, c).  -> [4, 4] float64."""
    rot = torch.eye(3, dtype=torch.float64)
    for axis, deg in enumerate(rotation_deg):
        phi = torch.zeros(3, dtype=torch.float64)
        phi[axis] = math.radians(deg)
        rot = so3_exp(phi) @ rot
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot
    out[:3, 3] = torch.tensor(translation, dtype=torch.float64)
    return out


# --------------------------------------------------------------------------------------------
# The split
# --------------------------------------------------------------------------------------------


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
    sec = _sectors(views, cfg, train_idx, len(ids))
    mem_train = _membership(sec.azimuth_deg.numpy()[train_idx], sec.starts, sec.width, sec.margin)  # [M_train, N]
    overlaps = _overlaps(mem_train)
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
        robots[rid] = _robot_split(views, cfg, rid, rid == reference, idx, gen, sector, float(overlaps[k]))

    seen_by = []
    if eval_idx:
        mem_eval = _membership(sec.azimuth_deg.numpy()[eval_idx], sec.starts, sec.width, sec.margin)
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
        mean_overlap=float(np.mean(overlaps)),
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


@dataclass
class _Sectors:
    center: Tensor  # [3]
    up: Tensor  # [3] unit
    azimuth_deg: Tensor  # [M] of every source view
    starts: np.ndarray  # [N] core sector starts, degrees
    width: float  # of a core sector, degrees
    margin: float  # delta, degrees


def _sectors(views: Views, cfg: SplitConfig, train_idx: list[int], n: int) -> _Sectors:
    """The robots' sectors about the up axis, widened by the margin that gives the requested overlap."""
    up = torch.tensor(cfg.up, dtype=torch.float64) if cfg.up is not None else mean_up(views.c2w)
    up = up / up.norm()
    center = torch.tensor(cfg.center, dtype=torch.float64) if cfg.center is not None else scene_center(views.c2w)
    az_all = azimuths_deg(views.c2w, center, up)
    width = 360.0 / n
    starts = (cfg.sector_start_deg + width * np.arange(n)) % 360.0
    delta = _choose_margin(az_all.numpy()[train_idx], starts, width, cfg.overlap)
    return _Sectors(center, up, az_all, starts, width, delta)


def _robot_split(views: Views, cfg: SplitConfig, rid: int, is_reference: bool, idx: list[int], gen: torch.Generator,
                 sector: tuple[float, float], overlap: float) -> RobotSplit:
    """Robot ``rid``'s views ``idx`` moved into its local frame, with its depth prior."""
    sub = views.subset(idx)
    t_wl = _local_frame(cfg, is_reference, sub, gen)
    scale = float(sim3_decompose(t_wl)[0])
    c2w_local = transform_c2w(sim3_inverse(t_wl), sub.c2w.to(torch.float64)).float()
    depth, affine = _depth_prior(cfg, sub, scale, gen) if cfg.depth_prior != "none" else (None, None)
    meta = {k2: v for k2, v in sub.meta.items() if k2 not in ("scene_box_world",)}
    meta.update(robot_id=rid, frame=cfg.frame, depth_prior=cfg.depth_prior)
    local = Views(sub.images, c2w_local, sub.intrinsics.clone(), list(sub.names), depth, meta)
    return RobotSplit(rid, local, idx, t_wl, sector, overlap, affine)


def _depth_prior(cfg: SplitConfig, sub: Views, scale: float, gen: torch.Generator) -> tuple[Tensor, Tensor | None]:
    """The robot's depth prior [M_i, H, W] in its local units, and the affine [M_i, 2] of a "scaled" one."""
    assert sub.depth is not None
    depth = sub.depth.to(torch.float64) / scale
    affine = None
    if cfg.depth_prior == "scaled":
        a = torch.empty(len(sub), dtype=torch.float64).uniform_(*cfg.depth_scale_range, generator=gen)
        b = torch.empty(len(sub), dtype=torch.float64).uniform_(*cfg.depth_shift_range, generator=gen)
        affine = torch.stack([a, b], -1)
        known = depth > 0
        depth = torch.where(known, (a[:, None, None] * depth + b[:, None, None]).clamp_min(1e-6), 0.0)
    return depth.float(), affine


def _local_frame(cfg: SplitConfig, is_reference: bool, sub: Views, gen: torch.Generator) -> Tensor:
    """T_world_from_local [4, 4] float64 of one robot."""
    if cfg.frame == "world":
        return torch.eye(4, dtype=torch.float64)
    if cfg.frame == "first_camera":
        return sub.c2w[0].to(torch.float64).clone()
    if cfg.frame == "offset":
        if is_reference:
            return torch.eye(4, dtype=torch.float64)
        return offset_transform(cfg.offset_rotation_deg, cfg.offset_translation)
    # random: rotation up to the max angle, translation uniform in the ball, optional scale
    out = torch.eye(4, dtype=torch.float64)
    rot = random_rotation(gen, cfg.random_max_angle_deg)
    direction = torch.randn(3, generator=gen, dtype=torch.float64)
    radius = cfg.random_max_translation * float(torch.rand((), generator=gen, dtype=torch.float64)) ** (1 / 3)
    log_s = math.log(cfg.random_max_scale)
    scale = math.exp((2 * float(torch.rand((), generator=gen, dtype=torch.float64)) - 1) * log_s) if log_s > 0 else 1.0
    out[:3, :3] = scale * rot
    out[:3, 3] = direction / direction.norm() * radius
    return out


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def robot_folder(split_dir: str | Path, robot_id: int) -> Path:
    """Robot ``robot_id``'s views in a split written by :func:`write_split`."""
    return Path(split_dir) / f"robot{robot_id}"


def _owned_outputs(out: Path) -> list[Path]:
    return sorted(out.glob("robot*")) + [out / n for n in ("eval", "truth.json", "split.json", "scene.json")]


def write_split(result: SplitResult, out: str | Path, *, overwrite: bool = False) -> Path:
    """Write robot folders, ``eval/``, ``truth.json``, ``split.json`` and ``scene.json`` under ``out``.

    An existing non-empty ``out`` is refused unless ``overwrite``, which removes only what a
    split writes (``robot*/``, ``eval/`` and the three json files) so that no stale robot of an
    earlier split with more robots survives.
    """
    out = Path(out)
    _prepare_output(out, overwrite)
    _write_view_folders(result, out)
    write_json(out / "truth.json", _truth(result))
    write_json(out / "split.json", _split_record(result))
    write_json(out / "scene.json", _scene(result))
    return out


def _prepare_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise DataError(f"{out}: folder is not empty; choose a new --out or pass --force to replace a previous split")
        for p in _owned_outputs(out):
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _write_view_folders(result: SplitResult, out: Path) -> None:
    """``robot<id>/`` (local frame; images only without poses) and ``eval/`` (world frame)."""
    cfg = result.config
    for rid, rob in result.robots.items():
        write_views_folder(
            rob.views,
            robot_folder(out, rid),
            write_poses=not cfg.images_only,
            top_extra={
                "dinerf": {
                    "robot_id": rid,
                    "frame": "local",
                    "depth_prior": cfg.depth_prior,
                    "depth_sparse": bool(rob.views.meta.get("depth_sparse", False)) and rob.views.depth is not None,
                }
            },
        )
        if cfg.calibrated_cameras:  # the camera's calibration, not a pose: what a robot knows of its camera
            from agent.data.sfm import write_camera_file

            write_camera_file(robot_folder(out, rid), float(rob.views.intrinsics[:, 0].median()), rob.views.width)
    if len(result.eval_indices):
        write_views_folder(
            result.eval_views,
            out / "eval",
            frame_extra=[{"seen_by": s} for s in result.seen_by],
            top_extra={
                "scene_box_world": {"center": result.box_center_world.tolist(), "half_size": result.box_half_size},
                "dinerf": {"frame": "world", "test_every": cfg.test_every},
            },
        )


def _truth(result: SplitResult) -> dict:
    """``truth.json``: what only the evaluation may read."""
    cfg = result.config
    t_shared = result.T_shared_from_local
    truth = {
        "note": "Evaluation only: the agents never read this file.",
        "reference_id": result.reference_id,
        "frame": cfg.frame,
        "shared_frame": f"local frame of robot {result.reference_id}",
        "scene_box_world": {"center": result.box_center_world.tolist(), "half_size": result.box_half_size},
        "robots": {},
    }
    if cfg.images_only:
        # A robot's local frame will be its own SfM's, unknown here: no T_world_from_local, but the
        # true world cameras of its views, to which the evaluation aligns its SfM cameras.
        truth["images_only"] = True
        truth["shared_frame"] = (f"the SfM frame of robot {result.reference_id}, made at run time; the evaluation "
                                 "calibrates every robot's SfM frame on cameras_world")
    for rid, rob in result.robots.items():
        entry: dict = {}
        if cfg.images_only:
            entry["cameras_world"] = {n: matrix_to_list(m) for n, m in zip(rob.views.names, rob.cameras_world)}
        else:
            entry = {
                "T_world_from_local": matrix_to_list(rob.T_world_from_local),
                "T_shared_from_local": matrix_to_list(t_shared[rid]),
                "scale": float(sim3_decompose(rob.T_world_from_local)[0]),
            }
        if rob.depth_affine is not None:
            entry["depth_affine"] = {
                "definition": "prior = a * true_local_z_depth + b (where the true depth is known)",
                "per_view": {n: [float(a), float(b)] for n, (a, b) in zip(rob.views.names, rob.depth_affine)},
            }
        truth["robots"][str(rid)] = entry
    return truth


def _split_record(result: SplitResult) -> dict:
    """``split.json``: how the split was made and what each robot got."""
    cfg = result.config
    return {
        "source": result.source,
        "config": dataclasses.asdict(cfg),
        "center": result.center.tolist(),
        "up": result.up.tolist(),
        "sector_margin_deg": result.margin_deg,
        "target_overlap": cfg.overlap,
        "mean_overlap": result.mean_overlap,
        "robots": {
            str(rid): {
                "count": len(rob.indices),
                "views": rob.views.names,
                "sector_deg": list(rob.sector_deg),
                "overlap": rob.overlap,
            }
            for rid, rob in result.robots.items()
        },
        "eval": {
            "test_every": cfg.test_every,
            "views": result.eval_views.names,
            "seen_by": result.seen_by,
        },
        "notes": result.notes,
    }


def _scene(result: SplitResult) -> dict:
    """``scene.json``: the shared frame's field box, which every robot reads."""
    if result.config.images_only:
        return {
            "reference_id": result.reference_id,
            "box_from_shared": None,
            "description": (
                "The robots have images only, so the shared frame g is the reference robot's own SfM frame, "
                "unknown when the data was split: the reference derives box_from_shared (g -> the normalised "
                "field box [-1, 1]^3) from its own SfM at start and shares it with its peers."
            ),
        }
    return {
        "reference_id": result.reference_id,
        "box_from_shared": matrix_to_list(result.box_from_shared),
        "description": (
            "box_from_shared maps the shared frame g (the local frame of the reference robot) into the "
            "normalised field box [-1, 1]^3; robot i maps its local points with box_from_shared @ T_i."
        ),
    }
