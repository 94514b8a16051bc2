"""The held-out views of a split and the truth they are scored against: each robot's frame in the world.

Only evaluation code reads the truth (``truth.json`` or a ``SplitResult``); the agents never do.
The shared frame g is the local frame of the split's reference robot, so the held-out views
(world frame) are mapped into g with ``inv(T_world_from_local[reference])`` and rendered by each
robot's field there: a robot whose field or pose is off in g scores badly, as it should.

Robots with images only have their own SfM frame as local frame, which the split cannot know.
Their ``T_world_from_local`` is calibrated after the run, as is standard for pose-free NeRF: a
Sim(3) fit of the robot's SfM camera centres to the true ones (:func:`calibrate_frame`). Its
residual bounds the accuracy of the evaluation itself, so it is reported.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from agent.data.views import DataError, Views
from agent.geometry import (
    box_from_center,
    rotation_angle_deg,
    sim3_decompose,
    sim3_inverse,
    transform_c2w,
    umeyama,
)


@dataclass
class FrameCalibration:
    """A robot's local (SfM) frame fitted to the world on its own cameras."""

    T_world_from_local: Tensor  # [4, 4] float64 Sim(3)
    matched: int  # the robot's cameras found in the truth (by name)
    inliers: int  # of them, those the final fit used
    centre_error_median: float  # world units: |fitted - true| camera centre, over the inliers
    rotation_error_median_deg: float  # camera orientation, fitted vs true (not used by the fit)
    # The robot's own focal length (its SfM's, as refined in training), in pixels at ``width``: a
    # frame fitted on camera centres only matches the scene through the camera that built it.
    focal_px: float | None = None
    width: int | None = None

    def summary(self) -> dict[str, float | int]:
        return {
            "matched": self.matched,
            "inliers": self.inliers,
            "centre_error_median": self.centre_error_median,
            "rotation_error_median_deg": self.rotation_error_median_deg,
            "scale": float(sim3_decompose(self.T_world_from_local)[0]),  # world units per SfM unit
            **({"focal_px": self.focal_px, "width": self.width} if self.focal_px is not None else {}),
        }


def calibrate_frame(
    names: list[str], c2w_local: Tensor, cameras_world: dict[str, Tensor], outlier_factor: float = 5.0
) -> FrameCalibration:
    """T_world_from_local by Umeyama on camera centres, matched by name.

    names: [M], c2w_local: [M, 4, 4] (the robot's cameras in its own frame), cameras_world: true
    c2w [4, 4] by name. After a first fit, cameras whose centre is off by more than
    ``outlier_factor`` x the median and more than 1% of the cameras' spread (a mis-registered SfM
    view, e.g. one mirrored through the object) are dropped and the fit is redone once, so that
    one bad view cannot tilt the frame every score is measured in.
    """
    idx = [j for j, n in enumerate(names) if n in cameras_world]
    if len(idx) < 3:
        raise DataError(f"calibrating a robot's frame needs >= 3 of its cameras in the truth, found {len(idx)}")
    local = c2w_local[idx].to(torch.float64)  # [K, 4, 4]
    world = torch.stack([torch.as_tensor(cameras_world[names[j]], dtype=torch.float64) for j in idx])  # [K, 4, 4]

    def fit(keep: Tensor) -> tuple[Tensor, Tensor]:
        t = umeyama(local[keep, :3, 3], world[keep, :3, 3])
        err = (transform_c2w(t, local)[:, :3, 3] - world[:, :3, 3]).norm(dim=-1)  # [K]
        return t, err

    keep = torch.ones(len(idx), dtype=torch.bool)
    t, err = fit(keep)
    centres = world[:, :3, 3]
    spread = float((centres - centres.mean(0)).norm(dim=-1).mean())
    inl = err <= max(outlier_factor * float(err.median()), 0.01 * spread)
    if not bool(inl.all()) and int(inl.sum()) >= 3:
        keep = inl
        t, err = fit(keep)
    fitted = transform_c2w(t, local[keep])
    rot = rotation_angle_deg(fitted[:, :3, :3], world[keep, :3, :3])  # [K']
    return FrameCalibration(
        T_world_from_local=t,
        matched=len(idx),
        inliers=int(keep.sum()),
        centre_error_median=float(err[keep].median()),
        rotation_error_median_deg=float(rot.median()),
    )


@dataclass
class EvalSet:
    views: Views  # held-out views in the world frame
    seen_by: list[list[int]]  # per view: robots whose sector contains it
    reference_id: int
    # [4, 4] float64 per robot: the truth of the split, or a calibration (robots with images only)
    T_world_from_local: dict[int, Tensor]
    # robots with images only: {id: {view name: true world c2w [4, 4]}}, to calibrate their frame on
    cameras_world: dict[int, dict[str, Tensor]] = field(default_factory=dict)
    box_from_world: Tensor | None = None  # [4, 4] world -> field box [-1, 1]^3 (the split's box)
    calibration: dict[int, FrameCalibration] = field(default_factory=dict)

    @property
    def needs_calibration(self) -> bool:
        """True when some robots' local frames are their own SfM frames (images only)."""
        return bool(self.cameras_world)

    def calibrate(self, robot_id: int, views: Views) -> FrameCalibration:
        """Fit robot ``robot_id``'s local frame to the world on ``views`` (its cameras, local frame)."""
        if robot_id not in self.cameras_world:
            raise DataError(f"robot {robot_id} has no cameras_world in the truth: its frame is known, not calibrated")
        cal = calibrate_frame(views.names, views.c2w, self.cameras_world[robot_id])
        cal.focal_px, cal.width = float(views.intrinsics[:, 0].median()), views.width
        self.calibration[robot_id] = cal
        self.T_world_from_local[robot_id] = cal.T_world_from_local
        return cal

    def has_frame(self, robot_id: int) -> bool:
        return robot_id in self.T_world_from_local

    def world_from_local(self, robot_id: int) -> Tensor:
        """Robot i's local frame -> world, with a clear error for an SfM frame not yet calibrated.  -> [4, 4]."""
        t = self.T_world_from_local.get(robot_id)
        if t is None:
            raise DataError(f"robot {robot_id}'s local frame is its own SfM frame: calibrate it first (EvalSet.calibrate)")
        return t

    @property
    def T_shared_from_world(self) -> Tensor:
        return sim3_inverse(self.world_from_local(self.reference_id))

    def T_shared_from_local(self, robot_id: int) -> Tensor:
        """What robot i's relative pose should converge to.  -> [4, 4] float64."""
        return self.T_shared_from_world @ self.world_from_local(robot_id)

    @property
    def box_from_shared(self) -> Tensor:
        """[4, 4]: shared frame g -> the split's field box (for a baseline that gets the frame for free)."""
        if self.box_from_world is None:
            raise DataError("this evaluation set has no scene box (truth.json without scene_box_world)")
        return self.box_from_world @ self.world_from_local(self.reference_id)

    def shared_cameras(self) -> Tensor:
        """The held-out cameras in the shared frame g.  -> [M, 4, 4]."""
        return transform_c2w(self.T_shared_from_world, self.views.c2w.double()).float()

    def shared_intrinsics(self, camera_of: int | None = None) -> Tensor:
        """The held-out views' intrinsics in the camera model of the frame the field was built in.  -> [M, 4]

        With known frames that is the truth. A swarm's field is built in the reference's SfM
        frame, with the focal length its SfM found (1-2% off on lego); after a Sim(3) fit on camera
        centres the scene only matches through that focal length, as test views registered into
        an SfM model get its intrinsics (measured on lego: 26.91 -> 29.02 dB for the reference).
        ``camera_of``: a robot trained alone in its own SfM frame (default: the reference).
        """
        k = self.views.intrinsics.clone()
        cal = self.calibration.get(self.reference_id if camera_of is None else camera_of)
        if cal is not None and cal.focal_px is not None:
            focal = cal.focal_px * self.views.width / cal.width
            k[:, 0] = focal
            k[:, 1] = focal * self.views.intrinsics[:, 1] / self.views.intrinsics[:, 0]
        return k

    def others_only(self, robot_id: int) -> list[int]:
        """Indices of held-out views that only other robots saw (outside this robot's sector)."""
        return [i for i, s in enumerate(self.seen_by) if robot_id not in s]

    @classmethod
    def from_split(cls, result) -> "EvalSet":
        """From an in-memory ``agent.data.split.SplitResult``."""
        if result.config.images_only:
            frames: dict[int, Tensor] = {}
            cams = {i: dict(zip(r.views.names, r.cameras_world)) for i, r in result.robots.items()}
        else:
            frames = {i: r.T_world_from_local.double() for i, r in result.robots.items()}
            cams = {}
        return cls(
            views=result.eval_views,
            seen_by=[list(s) for s in result.seen_by],
            reference_id=result.reference_id,
            T_world_from_local=frames,
            cameras_world=cams,
            box_from_world=result.box_from_world,
        )

    @classmethod
    def from_dir(cls, split_dir: str | Path, width: int | None = None) -> "EvalSet":
        """From a split folder written by ``dinerf-agent split`` (eval/ and truth.json)."""
        from agent.data.folder import read_truth
        from agent.data.loaders import load_views

        split_dir = Path(split_dir)
        eval_dir = split_dir / "eval"
        views = load_views(eval_dir, width=width)
        try:
            frames = json.loads((eval_dir / "transforms.json").read_text())["frames"]
            seen_by = [list(map(int, f.get("seen_by", []))) for f in frames]
        except (OSError, KeyError, ValueError, TypeError) as e:
            raise DataError(f"{eval_dir}: cannot read 'seen_by' of the held-out views: {e}") from None
        truth = read_truth(split_dir)
        try:
            robots = {int(i): r for i, r in truth["robots"].items()}
            cams = {
                i: {n: torch.tensor(m, dtype=torch.float64) for n, m in r["cameras_world"].items()}
                for i, r in robots.items() if "cameras_world" in r
            }
            poses = {i: r["T_world_from_local"] for i, r in robots.items() if i not in cams}
            ref = int(truth["reference_id"])
            box = truth.get("scene_box_world")
            box_from_world = box_from_center(torch.tensor(box["center"]), float(box["half_size"])) if box else None
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{split_dir}/truth.json: expected robots.* with T_world_from_local (or cameras_world) "
                            f"and reference_id: {e}") from None
        return cls(views=views, seen_by=seen_by, reference_id=ref, T_world_from_local=poses, cameras_world=cams,
                   box_from_world=box_from_world)
