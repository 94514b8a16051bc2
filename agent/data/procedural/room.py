"""A room around the procedural scene: textured walls, floor and ceiling far outside its box.

Real captures have a background, and a NeRF must either model it or keep it out of the scene's
box; an object on an empty black background tests neither. The room is an axis-aligned box
seen from inside: walls at ``|x|, |y| = ROOM_HALF_SIZE`` (7 units, 3.5 times the scene box),
the floor ``FLOOR_Z`` 0.55 under the base slab (which floats over it), the ceiling at
``CEILING_Z``. Every ray from a camera inside hits it, so the images have no background at all.
Its textures are smooth like the objects' (``tanh`` of sines) with periods of 1.6-2.4 units,
13-19 pixels at 64x64 seen head-on from the far side of the room (11 units), and each surface
has its own colours and phases, so that views of different walls do not look alike.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from agent.data.procedural.objects import Box, mix, soft

__all__ = ["ROOM", "ROOM_HALF_SIZE", "FLOOR_Z", "CEILING_Z", "room_sdf"]

ROOM_HALF_SIZE = 7.0
FLOOR_Z = -1.5
CEILING_Z = 5.5


def _pattern(a: np.ndarray, b: np.ndarray, period_a: float, period_b: float, phase: float) -> np.ndarray:
    """Soft checkers of half-periods ``period_a/2 x period_b/2`` in the surface's coordinates (a, b),
    modulated by a slow wave so that the checkers do not repeat exactly."""
    s = soft(np.sin(2 * math.pi * a / period_a + phase) * np.sin(2 * math.pi * b / period_b), 3.0)
    return s * (0.8 + 0.2 * np.sin(0.45 * a - 0.7 * b + phase))


# per surface (inward normal axis, sign): the two in-plane coordinates, periods, phase and colours
_SURFACES = {
    (2, +1): (0, 1, 2.0, 2.0, 0.0, [0.55, 0.42, 0.30], [0.85, 0.78, 0.62]),  # floor: wood and sand
    (2, -1): (0, 1, 2.4, 2.4, 1.0, [0.80, 0.80, 0.85], [0.95, 0.95, 0.90]),  # ceiling: pale greys
    (0, +1): (1, 2, 1.6, 2.0, 0.5, [0.70, 0.25, 0.20], [0.95, 0.80, 0.55]),  # wall at x = -7: brick and ochre
    (0, -1): (1, 2, 2.2, 1.6, 2.0, [0.20, 0.45, 0.30], [0.80, 0.90, 0.70]),  # wall at x = +7: greens
    (1, +1): (0, 2, 1.8, 2.4, 3.0, [0.25, 0.30, 0.60], [0.85, 0.85, 0.95]),  # wall at y = -7: blues
    (1, -1): (0, 2, 2.0, 1.8, 4.0, [0.55, 0.30, 0.55], [0.95, 0.85, 0.75]),  # wall at y = +7: plum and cream
}


class _Room(Box):
    """The room's box, seen from inside: the ray's exit point, normals pointing into the room."""

    def normal(self, p):
        return -super().normal(p)

    def albedo(self, p):
        n = self.normal(p)
        out = np.zeros_like(p)
        for (axis, sign), (ia, ib, pa, pb, phase, dark, light) in _SURFACES.items():
            sel = n[:, axis] * sign > 0.5
            if sel.any():
                out[sel] = mix(dark, light, _pattern(p[sel, ia], p[sel, ib], pa, pb, phase))
        return out


ROOM = _Room([0.0, 0.0, 0.5 * (FLOOR_Z + CEILING_Z)], [ROOM_HALF_SIZE, ROOM_HALF_SIZE, 0.5 * (CEILING_Z - FLOOR_Z)],
             0.0, None)


def room_sdf(points: Tensor | np.ndarray) -> Tensor:
    """Distance to the nearest wall, floor or ceiling, positive inside the room.  [N, 3] -> [N]."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return torch.from_numpy(-ROOM.sdf(p))
