"""How the procedural scene is photographed: :class:`ProceduralConfig` and its cameras."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agent.camera import focal_from_fov
from agent.data.views import DataError
from agent.geometry import look_at

__all__ = ["ProceduralConfig", "procedural_cameras"]


@dataclass
class ProceduralConfig:
    """How to photograph the procedural scene.

    Cameras look at the origin from ``radius`` with a horizontal field of view ``fov_deg``
    (40 deg and 4 units: close to the Blender scenes), at azimuths uniform in [0, 360) and
    elevations drawn uniformly *on the sphere* between ``elevation_deg`` (upper hemisphere, like
    the Blender training views), from ``seed``.
    """

    num_views: int = 100
    width: int = 64
    height: int = 64
    fov_deg: float = 40.0
    radius: float = 4.0
    elevation_deg: tuple[float, float] = (5.0, 75.0)
    seed: int = 0
    supersample: int = 3  # s x s rays per pixel, averaged (anti-aliased, as a camera sees); 1 = centre ray

    def __post_init__(self) -> None:
        if self.num_views < 1 or self.width < 1 or self.height < 1 or self.supersample < 1:
            raise DataError(f"procedural: num_views, width, height and supersample must be >= 1, got {self}")
        if not 1.0 <= self.fov_deg <= 170.0:
            raise DataError(f"procedural: fov_deg must be in [1, 170], got {self.fov_deg}")
        if self.radius <= 1.8:
            raise DataError(f"procedural: radius must exceed 1.8 (the scene box reaches sqrt(3)), got {self.radius}")
        lo, hi = self.elevation_deg
        if not -89.0 <= lo <= hi <= 89.0:
            raise DataError(f"procedural: elevation_deg must satisfy -89 <= lo <= hi <= 89, got {self.elevation_deg}")



def procedural_cameras(cfg: ProceduralConfig) -> tuple[Tensor, Tensor]:
    """The cameras of ``cfg``: c2w [M, 4, 4] float32 and intrinsics [M, 4] float32."""
    rng = np.random.default_rng(cfg.seed)
    az = rng.uniform(0.0, 2 * math.pi, cfg.num_views)
    lo, hi = (math.sin(math.radians(e)) for e in cfg.elevation_deg)
    el = np.arcsin(rng.uniform(lo, hi, cfg.num_views))
    eyes = cfg.radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    target = torch.zeros(3, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    c2w = torch.stack([look_at(torch.from_numpy(e), target, up) for e in eyes]).float()
    f = focal_from_fov(cfg.width, math.radians(cfg.fov_deg))
    intr = torch.tensor([[f, f, 0.5 * cfg.width, 0.5 * cfg.height]], dtype=torch.float32).repeat(cfg.num_views, 1)
    return c2w, intr

