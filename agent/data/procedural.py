"""The project's own scene: a few textured analytic objects, rendered exactly for any camera.

Why it exists: the demo, the quick start and the fast tests must run on a fresh clone with
nothing downloaded, and evaluation of novel views needs ground truth for *any* camera, not only
for the views of a dataset. Every pixel is exact: the mean of s x s rays spread over it
(``ProceduralConfig.supersample``, 3 by default), as a camera integrates light over the pixel and
as Blender's renders are anti-aliased; no noise. With point samples (s = 1, the ray through
``u + 0.5`` only) every silhouette is a hard 0/1 step, and a sub-pixel error in the learnt
geometry flips whole pixels: on held-out views at 64x64 such edge pixels held 95% of the error
and capped PSNR near 28 dB whatever the model.

The scene (z is up, like the Blender scenes) sits on a checkered base slab inside the box
``[-1, 1]^3``: a striped sphere, a rotated checkered box with a small sphere on top, a ringed
cylinder and a smoothly coloured ellipsoid. Textures vary smoothly (``tanh`` of sines, periods
of 0.3-0.5 scene units, i.e. several pixels at 64x64 from a radius of 4) so a small hash grid
can learn them; shading is Lambertian from a fixed light plus ambient, so colour is
view-independent. Alpha is the covered fraction of the pixel (RGB 0 where it is 0, straight
alpha); depth is the exact z-depth of the ray through the pixel centre, 0 where it misses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agent.camera import PIXEL_CENTRE, camera_directions, focal_from_fov
from agent.data.views import DataError, Views
from agent.geometry import look_at

__all__ = [
    "ProceduralConfig",
    "procedural_views",
    "render_procedural",
    "scene_sdf",
    "surface_colour",
    "SCENE_BOX_WORLD",
]

# The field box of the scene in world coordinates (centre, half-size): everything lies inside.
SCENE_BOX_WORLD = {"center": [0.0, 0.0, 0.0], "half_size": 1.0}
_LIGHT = np.array([0.5, 0.3, 1.0]) / np.linalg.norm([0.5, 0.3, 1.0])
_AMBIENT = 0.35
_EPS = 1e-9


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


# --------------------------------------------------------------------------------------------
# Texture helpers (all smooth: sharp edges in 3-D texture are what a hash grid learns worst)
# --------------------------------------------------------------------------------------------


def _soft(x: np.ndarray, k: float = 3.0) -> np.ndarray:
    """A soft square wave in [0, 1] from a signed value (``tanh`` instead of a hard sign)."""
    return 0.5 + 0.5 * np.tanh(k * x)


def _matmul3(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``p @ m`` for p: [N, 3], m: [3, 3], written out: numpy's matmul is slow for an inner size of 3."""
    return np.stack([p[:, 0] * m[0, j] + p[:, 1] * m[1, j] + p[:, 2] * m[2, j] for j in range(3)], -1)


def _mix(a, b, s: np.ndarray) -> np.ndarray:
    return np.asarray(a)[None, :] * (1 - s[:, None]) + np.asarray(b)[None, :] * s[:, None]


# --------------------------------------------------------------------------------------------
# Objects: ray intersection (t of o + t d; d need not be unit), SDF, normal and albedo
# --------------------------------------------------------------------------------------------


class _Sphere:
    def __init__(self, center, radius, albedo):
        self.c, self.r, self._albedo = np.asarray(center, float), float(radius), albedo

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = o - self.c
        a = (d * d).sum(-1)
        b = (oc * d).sum(-1)
        cc = (oc * oc).sum(-1) - self.r**2
        disc = b * b - a * cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = (-b - sq) / a, (-b + sq) / a
        t = np.where(t0 > _EPS, t0, t1)
        return np.where((disc >= 0) & (t > _EPS), t, np.inf)

    def sdf(self, p):
        return np.linalg.norm(p - self.c, axis=-1) - self.r

    def normal(self, p):
        n = p - self.c
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def albedo(self, p):
        return self._albedo(p, self)


class _Ellipsoid:
    def __init__(self, center, radii, albedo):
        self.c, self.radii, self._albedo = np.asarray(center, float), np.asarray(radii, float), albedo

    def intersect(self, o, d):
        return _Sphere(np.zeros(3), 1.0, None).intersect((o - self.c) / self.radii, d / self.radii)

    def sdf(self, p):
        # not an exact distance away from the surface, but exact zero set and first-order scale
        q = (p - self.c) / self.radii
        return (np.linalg.norm(q, axis=-1) - 1.0) * self.radii.min()

    def normal(self, p):
        n = (p - self.c) / self.radii**2
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def albedo(self, p):
        return self._albedo(p, self)


class _Box:
    """An oriented box: centre, half sizes, rotation about z by ``yaw_deg``."""

    def __init__(self, center, half, yaw_deg, albedo):
        self.c, self.h, self._albedo = np.asarray(center, float), np.asarray(half, float), albedo
        a = math.radians(yaw_deg)
        self.rot = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])

    def local(self, p):
        return _matmul3(p - self.c, self.rot)  # = R^T (p - c) row-wise

    def intersect(self, o, d):
        ol, dl = self.local(o), _matmul3(d, self.rot)
        # slab method, per axis with plain column arithmetic (reductions over a size-3 axis are slow);
        # a direction component of exactly 0 is nudged so that 1/d stays finite and signed
        dl = np.where(np.abs(dl) < 1e-30, 1e-30, dl)
        tmin, tmax = np.full(len(o), -np.inf), np.full(len(o), np.inf)
        for a in range(3):
            inv = 1.0 / dl[:, a]
            t1, t2 = (-self.h[a] - ol[:, a]) * inv, (self.h[a] - ol[:, a]) * inv
            tmin = np.maximum(tmin, np.minimum(t1, t2))
            tmax = np.minimum(tmax, np.maximum(t1, t2))
        t = np.where(tmin > _EPS, tmin, tmax)
        return np.where((tmin <= tmax) & (t > _EPS), t, np.inf)

    def sdf(self, p):
        q = np.abs(self.local(p)) - self.h
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)

    def normal(self, p):
        q = self.local(p) / self.h
        axis = np.abs(q).argmax(-1)
        n = np.zeros_like(q)
        n[np.arange(len(q)), axis] = np.sign(q[np.arange(len(q)), axis])
        return _matmul3(n, self.rot.T)

    def albedo(self, p):
        return self._albedo(p, self)


class _Cylinder:
    """A capped cylinder with a vertical axis through (x, y), from z0 to z1."""

    def __init__(self, center_xy, radius, z0, z1, albedo):
        self.cxy, self.r, self.z0, self.z1, self._albedo = np.asarray(center_xy, float), float(radius), z0, z1, albedo

    def intersect(self, o, d):
        ox, oy = o[:, 0] - self.cxy[0], o[:, 1] - self.cxy[1]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.r**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            z_side = o[:, 2] + t_side * dz
            side_ok = (disc >= 0) & (a > 0) & (t_side > _EPS) & (z_side >= self.z0) & (z_side <= self.z1)
            best = np.where(side_ok, t_side, np.inf)
            for zc in (self.z0, self.z1):
                tc = (zc - o[:, 2]) / dz
                x, y = ox + tc * dx, oy + tc * dy
                cap_ok = np.isfinite(tc) & (tc > _EPS) & (x * x + y * y <= self.r**2)
                best = np.minimum(best, np.where(cap_ok, tc, np.inf))
        return best

    def sdf(self, p):
        radial = np.linalg.norm(p[:, :2] - self.cxy, axis=-1) - self.r
        mid, half = 0.5 * (self.z0 + self.z1), 0.5 * (self.z1 - self.z0)
        axial = np.abs(p[:, 2] - mid) - half
        q = np.stack([radial, axial], -1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)

    def normal(self, p):
        radial = np.linalg.norm(p[:, :2] - self.cxy, axis=-1) - self.r
        mid, half = 0.5 * (self.z0 + self.z1), 0.5 * (self.z1 - self.z0)
        axial = np.abs(p[:, 2] - mid) - half
        side = np.concatenate([p[:, :2] - self.cxy, np.zeros((len(p), 1))], -1)
        side /= np.maximum(np.linalg.norm(side, axis=-1, keepdims=True), 1e-12)
        cap = np.zeros_like(p)
        cap[:, 2] = np.sign(p[:, 2] - mid)
        return np.where((radial > axial)[:, None], side, cap)

    def albedo(self, p):
        return self._albedo(p, self)


# Albedo functions (p: [N, 3] world points on the surface, obj: the object) -> [N, 3]


def _base_albedo(p, obj):  # soft checkers of 0.5 units on a cream/teal slab
    s = _soft(np.sin(math.pi * p[:, 0] / 0.5) * np.sin(math.pi * p[:, 1] / 0.5), 4.0)
    return _mix([0.93, 0.88, 0.72], [0.12, 0.45, 0.50], s)


def _sphere_albedo(p, obj):  # latitude stripes red/yellow, shaded a little along longitude
    n = (p - obj.c) / obj.r
    lat = np.arcsin(np.clip(n[:, 2], -1, 1))
    s = _soft(np.sin(8.0 * lat), 2.5)
    base = _mix([0.85, 0.15, 0.12], [0.98, 0.82, 0.20], s)
    return base * (0.8 + 0.2 * np.cos(np.arctan2(n[:, 1], n[:, 0])))[:, None]


def _box_albedo(p, obj):  # 3-D soft checkers of 0.2 units in the box frame, blue/white
    q = obj.local(p)
    s = _soft(np.sin(math.pi * q[:, 0] / 0.2) * np.sin(math.pi * q[:, 1] / 0.2) * np.sin(math.pi * q[:, 2] / 0.2 + 0.5), 4.0)
    return _mix([0.15, 0.25, 0.80], [0.92, 0.92, 0.95], s)


def _cylinder_albedo(p, obj):  # green-to-purple along the height, with soft rings
    h = (p[:, 2] - obj.z0) / (obj.z1 - obj.z0)
    grad = _mix([0.20, 0.70, 0.30], [0.55, 0.25, 0.70], np.clip(h, 0, 1))
    rings = _soft(np.sin(2 * math.pi * p[:, 2] / 0.3), 2.0)
    return grad * (0.65 + 0.35 * rings)[:, None]


def _ellipsoid_albedo(p, obj):  # smooth colour field, no edges at all
    return np.clip(0.5 + 0.4 * np.sin(3.0 * p[:, [0, 1, 2]] + np.array([0.0, 2.0, 4.0])), 0, 1)


def _top_sphere_albedo(p, obj):  # two-tone with a soft equator band
    n = (p - obj.c) / obj.r
    s = _soft(n[:, 2] * 3.0 - 0.2, 2.0)
    return _mix([0.95, 0.55, 0.15], [0.95, 0.95, 0.85], s)


_OBJECTS = (
    _Box([0.0, 0.0, -0.85], [0.9, 0.9, 0.1], 0.0, _base_albedo),
    _Sphere([0.4, 0.35, -0.35], 0.4, _sphere_albedo),
    _Box([-0.4, -0.3, -0.45], [0.3, 0.3, 0.3], 30.0, _box_albedo),
    _Sphere([-0.4, -0.3, 0.05], 0.2, _top_sphere_albedo),
    _Cylinder([0.45, -0.45], 0.2, -0.75, 0.45, _cylinder_albedo),
    _Ellipsoid([-0.35, 0.45, -0.3], [0.25, 0.25, 0.45], _ellipsoid_albedo),
)


# a box around all objects (slightly padded), used only to skip rays that hit nothing
_BOUNDS = _Box([0.0, 0.0, -0.25], [0.95, 0.95, 0.75], 0.0, None)


def _shade(obj, p: np.ndarray) -> np.ndarray:
    n = obj.normal(p)
    lambert = np.clip(n[:, 0] * _LIGHT[0] + n[:, 1] * _LIGHT[1] + n[:, 2] * _LIGHT[2], 0.0, None)
    return np.clip(obj.albedo(p) * (_AMBIENT + (1 - _AMBIENT) * lambert)[:, None], 0.0, 1.0)


def scene_sdf(points: Tensor | np.ndarray) -> Tensor:
    """Signed distance to the nearest object surface (negative inside).  points: [N, 3] -> [N].

    Exact for the spheres, boxes and cylinder; the ellipsoid term has the right zero set only.
    Useful for checks (a depth unprojected along its ray must land on a surface) and for
    ground-truth occupancy.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return torch.from_numpy(np.stack([o.sdf(p) for o in _OBJECTS], -1).min(-1))


def surface_colour(points: Tensor | np.ndarray) -> Tensor:
    """Shaded colour of the object whose surface is nearest to each point.  [N, 3] -> [N, 3]."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    which = np.abs(np.stack([o.sdf(p) for o in _OBJECTS], -1)).argmin(-1)
    out = np.zeros_like(p)
    for k, obj in enumerate(_OBJECTS):
        sel = which == k
        if sel.any():
            out[sel] = _shade(obj, p[sel])
    return torch.from_numpy(out)


# --------------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------------


def _trace(c2w: np.ndarray, k: np.ndarray, width: int, height: int, offset: tuple[float, float]):
    """One ray per pixel through (u + offset_u, v + offset_v): colour [M*H*W, 3], hit [M*H*W], z-depth t."""
    m = c2w.shape[0]
    u = np.arange(width) + offset[0]
    v = np.arange(height) + offset[1]
    # camera-frame directions with z = -1, so the hit parameter t *is* the z-depth
    dirs_cam = camera_directions(k[:, None, None, :], u[None, None, :], v[None, :, None])  # [M, H, W, 3]
    dirs = np.matmul(dirs_cam.reshape(m, -1, 3), c2w[:, :3, :3].transpose(0, 2, 1)).reshape(-1, 3)
    origins = np.repeat(c2w[:, :3, 3], height * width, axis=0)  # [M*H*W, 3]

    # Only rays through the bounding box of all objects can hit one: most pixels are background.
    t = np.full(len(dirs), np.inf)
    which = np.zeros(len(dirs), dtype=np.int64)
    live = np.nonzero(np.isfinite(_BOUNDS.intersect(origins, dirs)))[0]
    if len(live):
        ts = np.stack([obj.intersect(origins[live], dirs[live]) for obj in _OBJECTS], -1)  # [N_live, K]
        which[live] = ts.argmin(-1)
        t[live] = ts[np.arange(len(live)), which[live]]
    hit = np.isfinite(t)
    rgb = np.zeros((len(t), 3))
    for kk, obj in enumerate(_OBJECTS):
        sel = hit & (which == kk)
        if sel.any():
            rgb[sel] = _shade(obj, origins[sel] + t[sel, None] * dirs[sel])
    return rgb, hit, t


def render_procedural(c2w: Tensor, intrinsics: Tensor, width: int, height: int,
                      supersample: int = 1) -> tuple[Tensor, Tensor]:
    """Render the scene exactly for arbitrary cameras.

    c2w: [M, 4, 4] OpenGL camera-to-world; intrinsics: [M, 4] (fx, fy, cx, cy) in pixels.
    ``supersample`` s: each pixel is the mean of s x s rays spread evenly over it (a sensor
    integrating light over the pixel, anti-aliased like Blender's renders); 1: the ray through the
    pixel centre only. Returns rgba [M, H, W, 4] float32 (straight alpha = the covered fraction of
    the pixel, RGB 0 on the background) and depth [M, H, W] float32 (z-depth of the ray through
    the pixel centre, 0 where it hits nothing).
    """
    if type(supersample) is not int or supersample < 1:
        raise DataError(f"render_procedural: supersample must be an int >= 1, got {supersample!r}")
    c2w_np = np.asarray(torch.as_tensor(c2w), dtype=np.float64).reshape(-1, 4, 4)
    k = np.asarray(torch.as_tensor(intrinsics), dtype=np.float64).reshape(-1, 4)
    m = c2w_np.shape[0]
    if k.shape[0] != m:
        raise DataError(f"render_procedural: {m} poses but {k.shape[0]} intrinsics")
    centre = (PIXEL_CENTRE, PIXEL_CENTRE)
    rgb_c, hit_c, t_c = _trace(c2w_np, k, width, height, centre)
    depth = np.where(hit_c, t_c, 0.0)
    if supersample == 1:
        rgb, alpha = rgb_c, hit_c.astype(np.float64)
    else:
        premultiplied, alpha = np.zeros((len(t_c), 3)), np.zeros(len(t_c))
        for a in range(supersample):
            for b in range(supersample):
                offset = ((a + 0.5) / supersample, (b + 0.5) / supersample)
                rgb_s, hit_s, _ = (rgb_c, hit_c, t_c) if offset == centre else _trace(c2w_np, k, width, height, offset)
                premultiplied += rgb_s * hit_s[:, None]
                alpha += hit_s
        alpha /= supersample * supersample
        rgb = np.where(alpha[:, None] > 0, premultiplied / (supersample * supersample) / np.maximum(alpha, 1e-12)[:, None], 0.0)
    rgba = np.concatenate([rgb, alpha[:, None]], -1)
    return (
        torch.from_numpy(rgba.reshape(m, height, width, 4).astype(np.float32)),
        torch.from_numpy(depth.reshape(m, height, width).astype(np.float32)),
    )


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


def procedural_views(cfg: ProceduralConfig | None = None) -> Views:
    """The procedural dataset: ``cfg.num_views`` RGBA views with exact depth, deterministic in ``seed``."""
    cfg = cfg or ProceduralConfig()
    c2w, intr = procedural_cameras(cfg)
    rgba, depth = render_procedural(c2w, intr, cfg.width, cfg.height, cfg.supersample)
    return Views(
        images=rgba,
        c2w=c2w,
        intrinsics=intr,
        names=[f"view_{i:03d}" for i in range(cfg.num_views)],
        depth=depth,
        meta={
            "source": "procedural",
            "format": "procedural",
            "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(cfg).items()},
            "scene_box_world": dict(SCENE_BOX_WORLD),
            "depth_sparse": False,
            "depth_kind": "exact z-depth",
            "notes": [],
        },
    )
