"""A tiny textured scene rendered by ray casting, with exact cameras and z-depth.

Tests of SfM and alignment need images whose poses are known exactly and that do not depend on
../shared/data: a cube on a floor, every face covered by its own random multi-scale texture
(blobs and edges that SIFT latches onto), seen by cameras on a ring looking at the cube.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from agent.data.views import Views
from agent.geometry import look_at

CUBE = 1.0  # half side of the cube centred at the origin
FLOOR_Z = -1.0
FLOOR_HALF = 3.0


def _texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """[size, size, 3] float32 in [0, 1]: multi-octave noise plus random discs and bars."""
    tex = np.zeros((size, size, 3), np.float32)
    for octave, weight in ((4, 0.5), (16, 0.3), (64, 0.2)):
        noise = rng.random((octave, octave, 3)).astype(np.float32)
        tex += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        colour = tuple(float(c) for c in rng.random(3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        if rng.random() < 0.5:
            cv2.circle(tex, (x, y), int(rng.integers(4, 20)), colour, -1)
        else:
            cv2.rectangle(tex, (x, y), (x + int(rng.integers(4, 40)), y + int(rng.integers(4, 40))), colour, -1)
    return np.clip(tex, 0, 1)


class TexturedScene:
    """Cube + floor; :meth:`render` gives straight RGBA (alpha 0 where a ray hits nothing) and z-depth."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.textures = [_texture(rng) for _ in range(7)]  # 6 cube faces + floor

    def _shade(self, face: int, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        tex = self.textures[face]
        n = tex.shape[0]
        i = np.clip((t * (n - 1)).astype(int), 0, n - 1)
        j = np.clip((s * (n - 1)).astype(int), 0, n - 1)
        return tex[i, j]

    def render(self, c2w: np.ndarray, width: int, height: int, focal: float) -> tuple[np.ndarray, np.ndarray]:
        """OpenGL c2w [4, 4] -> (RGBA [H, W, 4] float32, z-depth [H, W] float32, 0 = background)."""
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        d_cam = np.stack([(u - width / 2) / focal, -(v - height / 2) / focal, -np.ones_like(u)], -1)
        dirs = d_cam @ c2w[:3, :3].T  # [H, W, 3], not normalised: t is then the z-depth
        orig = c2w[:3, 3]
        best_t = np.full(u.shape, np.inf)
        rgb = np.ones(u.shape + (3,), np.float32)
        # Cube: six faces, each a plane x_k = +-CUBE bounded in the other two coordinates.
        for axis in range(3):
            for side, sign in enumerate((-1.0, 1.0)):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = (sign * CUBE - orig[axis]) / dirs[..., axis]
                p = orig + dirs * t[..., None]
                o1, o2 = [k for k in range(3) if k != axis]
                hit = (t > 1e-6) & (np.abs(p[..., o1]) <= CUBE) & (np.abs(p[..., o2]) <= CUBE) & (t < best_t)
                face = 2 * axis + side
                col = self._shade(face, (p[..., o1] + CUBE) / (2 * CUBE), (p[..., o2] + CUBE) / (2 * CUBE))
                rgb[hit] = col[hit]
                best_t[hit] = t[hit]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (FLOOR_Z - orig[2]) / dirs[..., 2]
        p = orig + dirs * t[..., None]
        hit = (t > 1e-6) & (np.abs(p[..., 0]) <= FLOOR_HALF) & (np.abs(p[..., 1]) <= FLOOR_HALF) & (t < best_t)
        col = self._shade(6, (p[..., 0] + FLOOR_HALF) / (2 * FLOOR_HALF), (p[..., 1] + FLOOR_HALF) / (2 * FLOOR_HALF))
        rgb[hit] = col[hit]
        best_t[hit] = t[hit]
        alpha = np.isfinite(best_t).astype(np.float32)
        depth = np.where(np.isfinite(best_t), best_t, 0.0).astype(np.float32)
        return np.concatenate([rgb, alpha[..., None]], -1), depth


def ring_cameras(azimuths_deg: np.ndarray, radius: float = 5.0, height: float = 2.0) -> np.ndarray:
    """[N] azimuths -> OpenGL c2w [N, 4, 4] on a ring, looking at the cube, +Z up."""
    out = []
    for a in np.radians(np.asarray(azimuths_deg, dtype=np.float64)):
        eye = torch.tensor([radius * math.cos(a), radius * math.sin(a), height], dtype=torch.float64)
        out.append(look_at(eye, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).numpy())
    return np.stack(out)


def render_views(scene: TexturedScene, c2w: np.ndarray, width: int = 160, height: int = 120,
                 focal: float = 150.0) -> Views:
    """Views (RGBA + true z-depth) of the scene from the given cameras."""
    imgs, depths = zip(*(scene.render(c, width, height, focal) for c in c2w))
    n = len(c2w)
    return Views(
        images=torch.from_numpy(np.stack(imgs)),
        c2w=torch.from_numpy(c2w).float(),
        intrinsics=torch.tensor([[focal, focal, width / 2, height / 2]] * n, dtype=torch.float32),
        names=[f"v{i:03d}" for i in range(n)],
        depth=torch.from_numpy(np.stack(depths)),
        meta={"depth_metric": True},
    )


def save_rgba(views: Views, folder) -> None:
    """Write the views as RGBA PNG files (as a robot folder with images only would hold them)."""
    folder.mkdir(parents=True, exist_ok=True)
    for img, name in zip(views.images.numpy(), views.names):
        out = np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / f"{name}.png"), out[:, :, [2, 1, 0, 3]])
