"""Exact rendering of the procedural scene for any camera: anti-aliased colour, alpha, z-depth.

Every pixel is exact: the mean of s x s rays spread over it (``supersample``), as a camera
integrates light over the pixel and as Blender's renders are anti-aliased; no noise. With point
samples (s = 1, the ray through ``u + 0.5`` only) every silhouette is a hard 0/1 step, and a
sub-pixel error in the learnt geometry flips whole pixels: on held-out views at 64x64 such edge
pixels held 95% of the error and capped PSNR near 28 dB whatever the model.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from agent.camera import PIXEL_CENTRE, camera_directions
from agent.data.procedural.room import ROOM
from agent.data.procedural.scene import BOUNDS, OBJECTS, shade, surfaces
from agent.data.views import DataError

__all__ = ["render_procedural"]


Lens = tuple[float, float, float, float]  # (k1, k2, p1, p2), agent.camera's distortion model


def _trace(c2w: np.ndarray, k: np.ndarray, width: int, height: int, offset: tuple[float, float], room: bool,
           distortion: Lens | None):
    """One ray per pixel through (u + offset_u, v + offset_v): colour [M*H*W, 3], hit [M*H*W], z-depth t."""
    m = c2w.shape[0]
    u = np.arange(width) + offset[0]
    v = np.arange(height) + offset[1]
    # camera-frame directions with z = -1, so the hit parameter t *is* the z-depth
    dirs_cam = camera_directions(k[:, None, None, :], u[None, None, :], v[None, :, None], distortion)  # [M, H, W, 3]
    dirs = np.matmul(dirs_cam.reshape(m, -1, 3), c2w[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(c2w[:, :3, 3], height * width, axis=0)  # [M*H*W, 3]

    # Only rays through the bounding box of all objects can hit one: most pixels are background.
    t = np.full(len(dirs), np.inf)
    which = np.zeros(len(dirs), dtype=np.int64)
    live = np.nonzero(np.isfinite(BOUNDS.intersect(origins, dirs)))[0]
    if len(live):
        ts = np.stack([obj.intersect(origins[live], dirs[live]) for obj in OBJECTS], -1)  # [N_live, K]
        which[live] = ts.argmin(-1)
        t[live] = ts[np.arange(len(live)), which[live]]
    if room:  # every ray that misses the objects ends on a wall, the floor or the ceiling
        t_room = ROOM.intersect(origins, dirs)
        behind = t_room < t
        which[behind], t[behind] = len(OBJECTS), t_room[behind]
    hit = np.isfinite(t)
    rgb = np.zeros((len(t), 3))
    for kk, obj in enumerate(surfaces(room)):
        sel = hit & (which == kk)
        if sel.any():
            rgb[sel] = shade(obj, origins[sel] + t[sel, None] * dirs[sel])
    return rgb, hit, t


def render_procedural(c2w: Tensor, intrinsics: Tensor, width: int, height: int, supersample: int = 1, *,
                      room: bool = False, distortion: Lens | None = None) -> tuple[Tensor, Tensor]:
    """Render the scene exactly for arbitrary cameras.

    c2w: [M, 4, 4] OpenGL camera-to-world; intrinsics: [M, 4] (fx, fy, cx, cy) in pixels.
    ``supersample`` s: each pixel is the mean of s x s rays spread evenly over it (a sensor
    integrating light over the pixel, anti-aliased like Blender's renders); 1: the ray through the
    pixel centre only. ``room``: the room of :mod:`.room` around the scene (cameras inside it).
    ``distortion`` (k1, k2, p1, p2): what a lens with OpenCV's radial-tangential distortion
    records, every ray through the undistorted position of its point of the sensor.
    Returns rgba [M, H, W, 4] float32 (straight alpha = the covered fraction of the pixel, RGB 0
    on the background; 1 everywhere with the room) and depth [M, H, W] float32 (z-depth of the
    ray through the pixel centre, 0 where it hits nothing).
    """
    if type(supersample) is not int or supersample < 1:
        raise DataError(f"render_procedural: supersample must be an int >= 1, got {supersample!r}")
    c2w_np = np.asarray(torch.as_tensor(c2w), dtype=np.float64).reshape(-1, 4, 4)
    k = np.asarray(torch.as_tensor(intrinsics), dtype=np.float64).reshape(-1, 4)
    m = c2w_np.shape[0]
    if k.shape[0] != m:
        raise DataError(f"render_procedural: {m} poses but {k.shape[0]} intrinsics")
    centre = (PIXEL_CENTRE, PIXEL_CENTRE)
    rgb_c, hit_c, t_c = _trace(c2w_np, k, width, height, centre, room, distortion)
    depth = np.where(hit_c, t_c, 0.0)
    if supersample == 1:
        rgb, alpha = rgb_c, hit_c.astype(np.float64)
    else:
        premultiplied, alpha = np.zeros((len(t_c), 3)), np.zeros(len(t_c))
        for a in range(supersample):
            for b in range(supersample):
                offset = ((a + 0.5) / supersample, (b + 0.5) / supersample)
                rgb_s, hit_s, _ = ((rgb_c, hit_c, t_c) if offset == centre
                                   else _trace(c2w_np, k, width, height, offset, room, distortion))
                premultiplied += rgb_s * hit_s[:, None]
                alpha += hit_s
        alpha /= supersample * supersample
        rgb = np.where(alpha[:, None] > 0, premultiplied / (supersample * supersample) / np.maximum(alpha, 1e-12)[:, None], 0.0)
    rgba = np.concatenate([rgb, alpha[:, None]], -1)
    return (
        torch.from_numpy(rgba.reshape(m, height, width, 4).astype(np.float32)),
        torch.from_numpy(depth.reshape(m, height, width).astype(np.float32)),
    )
