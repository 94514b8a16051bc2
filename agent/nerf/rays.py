"""Camera rays from posed pixels, in the camera's world frame (conventions: :mod:`agent.camera`).

Rays are built from camera-to-world matrices so that a pose transform applied to ``c2w``
(``agent.geometry.transform_c2w``) is differentiated through the ray origins and directions.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from agent.camera import camera_directions, pixel_centre


@dataclass
class Rays:
    origins: Tensor  # [R, 3]
    directions: Tensor  # [R, 3] unit length
    z_per_t: Tensor  # [R] z-depth per unit of distance along the ray (cos of the off-axis angle)

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def __getitem__(self, index) -> "Rays":
        return Rays(self.origins[index], self.directions[index], self.z_per_t[index])


def pixel_rays(c2w: Tensor, intrinsics: Tensor, u: Tensor, v: Tensor) -> Rays:
    """Rays through pixel positions.

    c2w: [R, 4, 4], intrinsics: [R, 4] (fx, fy, cx, cy), u, v: [R] pixel coordinates (pixel
    centres at i + 0.5, :mod:`agent.camera`).
    """
    d_cam = camera_directions(intrinsics, u, v)  # [R, 3], z = -1
    norm = d_cam.norm(dim=-1)  # [R]
    d_world = (c2w[:, :3, :3] @ (d_cam / norm[:, None])[:, :, None]).squeeze(-1)
    return Rays(origins=c2w[:, :3, 3], directions=d_world, z_per_t=1.0 / norm)


def image_rays(c2w: Tensor, intrinsics: Tensor, width: int, height: int) -> Rays:
    """All pixel-centre rays of one image, row-major.  c2w: [4, 4], intrinsics: [4] -> R = H * W."""
    device = c2w.device
    jj, ii = torch.meshgrid(
        torch.arange(height, device=device, dtype=c2w.dtype),
        torch.arange(width, device=device, dtype=c2w.dtype),
        indexing="ij",
    )
    u = pixel_centre(ii).reshape(-1)
    v = pixel_centre(jj).reshape(-1)
    n = u.numel()
    return pixel_rays(c2w[None].expand(n, 4, 4), intrinsics[None].expand(n, 4), u, v)


def transform_rays(rays: Rays, transform: Tensor) -> Rays:
    """Map rays by a similarity ``x -> s R x + t`` (e.g. shared frame -> box).

    Directions stay unit; distances along the ray scale by ``s``, so ``z_per_t`` (z-depth in the
    source frame per unit t in the target frame) is divided by ``s``.
    """
    sr = transform[:3, :3]
    scale = torch.linalg.det(sr).abs().pow(1.0 / 3.0)
    origins = rays.origins @ sr.T + transform[:3, 3]
    directions = rays.directions @ (sr / scale).T
    return Rays(origins, directions, rays.z_per_t / scale)
