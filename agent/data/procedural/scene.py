"""The objects of the procedural scene, their textures and their shading.

The scene (z is up, like the Blender scenes) sits on a checkered base slab inside the box
``[-1, 1]^3``: a striped sphere, a rotated checkered box with a small sphere on top, a ringed
cylinder and a smoothly coloured ellipsoid. Textures vary smoothly (``tanh`` of sines, periods
of 0.3-0.5 scene units, i.e. several pixels at 64x64 from a radius of 4) so a small hash grid
can learn them; shading is Lambertian from a fixed light plus ambient, so colour is
view-independent.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from agent.data.procedural.objects import Box, Cylinder, Ellipsoid, Sphere, mix, soft
from agent.data.procedural.room import ROOM

__all__ = ["SCENE_BOX_WORLD", "OBJECTS", "BOUNDS", "shade", "surfaces", "scene_sdf", "surface_colour"]

# The field box of the scene in world coordinates (centre, half-size): everything lies inside.
SCENE_BOX_WORLD = {"center": [0.0, 0.0, 0.0], "half_size": 1.0}
_LIGHT = np.array([0.5, 0.3, 1.0]) / np.linalg.norm([0.5, 0.3, 1.0])
_AMBIENT = 0.35


# Albedo functions (p: [N, 3] world points on the surface, obj: the object) -> [N, 3]


def _base_albedo(p, obj):  # soft checkers of 0.5 units on a cream/teal slab
    s = soft(np.sin(math.pi * p[:, 0] / 0.5) * np.sin(math.pi * p[:, 1] / 0.5), 4.0)
    return mix([0.93, 0.88, 0.72], [0.12, 0.45, 0.50], s)


def _sphere_albedo(p, obj):  # latitude stripes red/yellow, shaded a little along longitude
    n = (p - obj.c) / obj.r
    lat = np.arcsin(np.clip(n[:, 2], -1, 1))
    s = soft(np.sin(8.0 * lat), 2.5)
    base = mix([0.85, 0.15, 0.12], [0.98, 0.82, 0.20], s)
    return base * (0.8 + 0.2 * np.cos(np.arctan2(n[:, 1], n[:, 0])))[:, None]


def _box_albedo(p, obj):  # 3-D soft checkers of 0.2 units in the box frame, blue/white
    q = obj.local(p)
    s = soft(np.sin(math.pi * q[:, 0] / 0.2) * np.sin(math.pi * q[:, 1] / 0.2) * np.sin(math.pi * q[:, 2] / 0.2 + 0.5), 4.0)
    return mix([0.15, 0.25, 0.80], [0.92, 0.92, 0.95], s)


def _cylinder_albedo(p, obj):  # green-to-purple along the height, with soft rings
    h = (p[:, 2] - obj.z0) / (obj.z1 - obj.z0)
    grad = mix([0.20, 0.70, 0.30], [0.55, 0.25, 0.70], np.clip(h, 0, 1))
    rings = soft(np.sin(2 * math.pi * p[:, 2] / 0.3), 2.0)
    return grad * (0.65 + 0.35 * rings)[:, None]


def _ellipsoid_albedo(p, obj):  # smooth colour field, no edges at all
    return np.clip(0.5 + 0.4 * np.sin(3.0 * p[:, [0, 1, 2]] + np.array([0.0, 2.0, 4.0])), 0, 1)


def _top_sphere_albedo(p, obj):  # two-tone with a soft equator band
    n = (p - obj.c) / obj.r
    s = soft(n[:, 2] * 3.0 - 0.2, 2.0)
    return mix([0.95, 0.55, 0.15], [0.95, 0.95, 0.85], s)


OBJECTS = (
    Box([0.0, 0.0, -0.85], [0.9, 0.9, 0.1], 0.0, _base_albedo),
    Sphere([0.4, 0.35, -0.35], 0.4, _sphere_albedo),
    Box([-0.4, -0.3, -0.45], [0.3, 0.3, 0.3], 30.0, _box_albedo),
    Sphere([-0.4, -0.3, 0.05], 0.2, _top_sphere_albedo),
    Cylinder([0.45, -0.45], 0.2, -0.75, 0.45, _cylinder_albedo),
    Ellipsoid([-0.35, 0.45, -0.3], [0.25, 0.25, 0.45], _ellipsoid_albedo),
)


# a box around all objects (slightly padded), used only to skip rays that hit nothing
BOUNDS = Box([0.0, 0.0, -0.25], [0.95, 0.95, 0.75], 0.0, None)


def shade(obj, p: np.ndarray) -> np.ndarray:
    n = obj.normal(p)
    lambert = np.clip(n[:, 0] * _LIGHT[0] + n[:, 1] * _LIGHT[1] + n[:, 2] * _LIGHT[2], 0.0, None)
    return np.clip(obj.albedo(p) * (_AMBIENT + (1 - _AMBIENT) * lambert)[:, None], 0.0, 1.0)


def surfaces(room: bool = False) -> tuple:
    """What a ray can hit: the objects, and the room around them (:mod:`.room`) if ``room``."""
    return OBJECTS + (ROOM,) if room else OBJECTS


def _signed_distances(p: np.ndarray, room: bool) -> np.ndarray:
    """[N, K] signed distance to each surface, negative inside solid matter (beyond the room's walls)."""
    return np.stack([-s.sdf(p) if s is ROOM else s.sdf(p) for s in surfaces(room)], -1)


def scene_sdf(points: Tensor | np.ndarray, room: bool = False) -> Tensor:
    """Signed distance to the nearest surface (negative inside matter).  points: [N, 3] -> [N].

    Exact for the spheres, boxes, cylinder and room; the ellipsoid term has the right zero set
    only. Useful for checks (a depth unprojected along its ray must land on a surface) and for
    ground-truth occupancy.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return torch.from_numpy(_signed_distances(p, room).min(-1))


def surface_colour(points: Tensor | np.ndarray, room: bool = False) -> Tensor:
    """Shaded colour of the surface nearest to each point.  [N, 3] -> [N, 3]."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    which = np.abs(_signed_distances(p, room)).argmin(-1)
    out = np.zeros_like(p)
    for k, obj in enumerate(surfaces(room)):
        sel = which == k
        if sel.any():
            out[sel] = shade(obj, p[sel])
    return torch.from_numpy(out)

