"""Camera paths to render a field along: an orbit or a spiral around its box, in the shared frame.

The defaults come from the robot's own cameras, so that a path looks at the scene from where it
was filmed: the radius is the median distance of the cameras from the box centre, the elevation
their median elevation above the plane orthogonal to their up axis (``agent.data.capture.mean_up``),
and the path starts at the first camera's azimuth. Cameras are OpenGL c2w (``agent.camera``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from agent.config_io import InvalidValue, check
from agent.data.capture import mean_up
from agent.geometry import sim3_decompose, sim3_inverse

__all__ = ["OrbitConfig", "look_at", "box_centre", "orbit_poses", "path_intrinsics", "trainer_orbit"]


@dataclass
class OrbitConfig:
    frames: int = 60
    elevation_deg: float | None = None  # above the cameras' horizontal plane; None: their median
    radius: float | None = None  # shared-frame units from the box centre; None: the cameras' median distance
    spiral_deg: float = 0.0  # the elevation swings +- this once per turn (0: a circle)
    turns: float = 1.0

    def __post_init__(self) -> None:
        check(self, frames=">= 1", spiral_deg=">= 0", turns="> 0")
        if self.radius is not None and not self.radius > 0:
            raise InvalidValue("radius", f"must be > 0, got {self.radius!r}")
        if self.elevation_deg is not None and not -90 < self.elevation_deg < 90:
            raise InvalidValue("elevation_deg", f"must be in (-90, 90), got {self.elevation_deg!r}")


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """An OpenGL camera at ``eye`` looking at ``target`` (its -Z axis), roll-free about ``up``.  [3] x3 -> [4, 4]."""
    back = eye - target
    back = back / back.norm()
    right = torch.linalg.cross(up, back)
    if right.norm() < 1e-9:  # looking straight along up: any right axis will do
        right = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=eye.dtype), back)
    right = right / right.norm()
    cam_up = torch.linalg.cross(back, right)
    c2w = torch.eye(4, dtype=eye.dtype)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def box_centre(box_from_shared: Tensor) -> tuple[Tensor, float]:
    """The field box's centre [3] in the shared frame, and its half size there (shared units)."""
    shared_from_box = sim3_inverse(box_from_shared.double())
    return shared_from_box[:3, 3], 1.0 / float(sim3_decompose(box_from_shared.double())[0])


def orbit_poses(cameras: Tensor, box_from_shared: Tensor, cfg: OrbitConfig) -> Tensor:
    """``cfg.frames`` cameras around the box, looking at its centre.  cameras: [M, 4, 4] shared -> [N, 4, 4]."""
    cameras = cameras.double().cpu()
    centre, _ = box_centre(box_from_shared.cpu())
    up = mean_up(cameras)
    offsets = cameras[:, :3, 3] - centre  # [M, 3]
    dist = offsets.norm(dim=-1).clamp_min(1e-9)  # [M]
    radius = cfg.radius if cfg.radius is not None else float(dist.median())
    if cfg.elevation_deg is not None:
        elevation = math.radians(cfg.elevation_deg)
    else:
        elevation = float(torch.asin((offsets @ up / dist).clamp(-1, 1)).median())
    flat = offsets[0] - (offsets[0] @ up) * up  # the first camera's azimuth
    if flat.norm() < 1e-6 * float(dist[0]):
        axis = torch.zeros(3, dtype=torch.float64)
        axis[int(up.abs().argmin())] = 1.0
        flat = axis - (axis @ up) * up
    e1 = flat / flat.norm()
    e2 = torch.linalg.cross(up, e1)
    poses = []
    for k in range(cfg.frames):
        phase = k / cfg.frames
        azimuth = 2 * math.pi * cfg.turns * phase
        el = elevation + math.radians(cfg.spiral_deg) * math.sin(2 * math.pi * phase)
        direction = math.cos(el) * (math.cos(azimuth) * e1 + math.sin(azimuth) * e2) + math.sin(el) * up
        poses.append(look_at(centre + radius * direction, centre, up))
    return torch.stack(poses).float()


def path_intrinsics(intrinsics: Tensor, width: int, height: int, out_width: int | None) -> tuple[Tensor, int, int]:
    """Intrinsics [4] for a path rendered ``out_width`` wide, from the robot's views' ([M, 4] at width x height).

    The median focal length, scaled; the principal point at the image centre. -> (k [4], width, height)."""
    scale = 1.0 if out_width is None else out_width / width
    w, h = max(round(width * scale), 1), max(round(height * scale), 1)
    f = intrinsics[:, :2].double().median(dim=0).values * scale
    return torch.tensor([float(f[0]), float(f[1]), w / 2, h / 2]), w, h


def trainer_orbit(trainer, cfg: OrbitConfig, out_width: int | None) -> tuple[Tensor, Tensor, int, int]:
    """The orbit around a robot's field box, from its own cameras and focal length (``agent.trainer.RobotTrainer``).

    -> (c2w [N, 4, 4] shared frame, intrinsics [N, 4], width, height)"""
    own = trainer.cameras_shared().detach().cpu()
    c2w = orbit_poses(own, trainer.box_from_shared, cfg)
    k, w, h = path_intrinsics(trainer.camera_intrinsics().detach().cpu(), trainer.views.width, trainer.views.height,
                              out_width)
    return c2w, k.expand(len(c2w), 4), w, h
