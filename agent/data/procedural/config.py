"""How the procedural scene is photographed: :class:`ProceduralConfig` and its cameras."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agent.camera import DISTORTION_KEYS, distort, distortion_coeffs, focal_from_fov, undistort
from agent.data.procedural.room import CEILING_Z, FLOOR_Z, ROOM_HALF_SIZE
from agent.data.views import DataError
from agent.geometry import look_at

__all__ = ["ProceduralConfig", "procedural_cameras"]

MAX_SIDE = 4096  # a synthetic test scene: anything larger is a typo, and would exhaust memory
MAX_RAYS = 2e8


@dataclass
class ProceduralConfig:
    """How to photograph the procedural scene.

    Cameras look at the origin from ``radius`` with a horizontal field of view ``fov_deg``
    (40 deg and 4 units: close to the Blender scenes), at azimuths uniform in [0, 360) and
    elevations drawn uniformly *on the sphere* between ``elevation_deg`` (upper hemisphere, like
    the Blender training views), from ``seed``.

    ``arc_deg``: azimuths uniform on the arc ``[arc_start_deg, arc_start_deg + arc_deg)`` instead,
    and the views in capture order along it (names and order by increasing azimuth), as a
    handheld capture walking round part of the scene records them. ``room``: walls, floor and
    ceiling around the scene (:mod:`.room`): the images are RGB, every pixel sees something.
    ``k1, k2, p1, p2``: the lens distorts (OpenCV's radial-tangential model, :mod:`agent.camera`).
    """

    num_views: int = 100
    width: int = 64
    height: int = 64
    fov_deg: float = 40.0
    radius: float = 4.0
    elevation_deg: tuple[float, float] = (5.0, 75.0)
    seed: int = 0
    supersample: int = 3  # s x s rays per pixel, averaged (anti-aliased, as a camera sees); 1 = centre ray
    arc_deg: float | None = None  # None: anywhere on the circle, in random order
    arc_start_deg: float = 0.0
    room: bool = False
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        if self.num_views < 1 or self.width < 1 or self.height < 1 or self.supersample < 1:
            raise DataError(f"procedural: num_views, width, height and supersample must be >= 1, got {self}")
        pixels = self.num_views * self.width * self.height * self.supersample ** 2
        if max(self.width, self.height) > MAX_SIDE or pixels > MAX_RAYS:
            raise DataError(f"procedural: at most {MAX_SIDE} px a side and {MAX_RAYS:.0e} rays in all "
                            f"(views x width x height x supersample^2), got {pixels:.2g}: it would not fit in memory")
        if not 1.0 <= self.fov_deg <= 170.0:
            raise DataError(f"procedural: fov_deg must be in [1, 170], got {self.fov_deg}")
        if self.radius <= 1.8:
            raise DataError(f"procedural: radius must exceed 1.8 (the scene box reaches sqrt(3)), got {self.radius}")
        lo, hi = self.elevation_deg
        if not -89.0 <= lo <= hi <= 89.0:
            raise DataError(f"procedural: elevation_deg must satisfy -89 <= lo <= hi <= 89, got {self.elevation_deg}")
        if self.arc_deg is not None and not 0.0 < self.arc_deg <= 360.0:
            raise DataError(f"procedural: arc_deg must be in (0, 360], got {self.arc_deg}")
        if self.room:
            self._check_inside_room()
        if self.distortion is not None:
            self._check_lens()

    @property
    def distortion(self) -> tuple[float, float, float, float] | None:
        """(k1, k2, p1, p2), or None for a pinhole lens."""
        return distortion_coeffs({k: getattr(self, k) for k in DISTORTION_KEYS})

    def _check_inside_room(self) -> None:
        lo, hi = (self.radius * math.sin(math.radians(e)) for e in self.elevation_deg)
        margin = 0.25  # a camera on a wall would see half the room from behind its plaster
        if self.radius > ROOM_HALF_SIZE - margin or lo < FLOOR_Z + margin or hi > CEILING_Z - margin:
            raise DataError(f"procedural: with room=1 the cameras must stay inside the room (|x|, |y| < "
                            f"{ROOM_HALF_SIZE - margin}, {FLOOR_Z + margin} < z < {CEILING_Z - margin}); radius "
                            f"{self.radius} at elevations {self.elevation_deg} leaves it")

    def _check_lens(self) -> None:
        """The distortion must be invertible over the whole image (else no ray is defined there)."""
        f = focal_from_fov(self.width, math.radians(self.fov_deg))
        border = np.concatenate([np.stack([np.linspace(0, self.width, 64), np.full(64, y)], -1) for y in (0, self.height)]
                                + [np.stack([np.full(64, x), np.linspace(0, self.height, 64)], -1) for x in (0, self.width)])
        xd, yd = (border[:, 0] - 0.5 * self.width) / f, (border[:, 1] - 0.5 * self.height) / f
        x, y = undistort(xd, yd, self.distortion)
        back = distort(x, y, self.distortion)
        if not (np.isfinite(x).all() and np.abs(back[0] - xd).max() < 1e-9 and np.abs(back[1] - yd).max() < 1e-9):
            raise DataError(f"procedural: the lens (k1, k2, p1, p2) = {self.distortion} cannot be inverted over a "
                            f"{self.width}x{self.height} image with a {self.fov_deg} deg field of view; use smaller coefficients")


def procedural_cameras(cfg: ProceduralConfig) -> tuple[Tensor, Tensor]:
    """The cameras of ``cfg`` (on an arc: in capture order): c2w [M, 4, 4] float32 and intrinsics [M, 4] float32."""
    rng = np.random.default_rng(cfg.seed)
    if cfg.arc_deg is None:
        az = rng.uniform(0.0, 2 * math.pi, cfg.num_views)
    else:
        az = np.radians(cfg.arc_start_deg + np.sort(rng.uniform(0.0, cfg.arc_deg, cfg.num_views)))
    lo, hi = (math.sin(math.radians(e)) for e in cfg.elevation_deg)
    el = np.arcsin(rng.uniform(lo, hi, cfg.num_views))
    eyes = cfg.radius * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    target = torch.zeros(3, dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    c2w = torch.stack([look_at(torch.from_numpy(e), target, up) for e in eyes]).float()
    f = focal_from_fov(cfg.width, math.radians(cfg.fov_deg))
    intr = torch.tensor([[f, f, 0.5 * cfg.width, 0.5 * cfg.height]], dtype=torch.float32).repeat(cfg.num_views, 1)
    return c2w, intr
