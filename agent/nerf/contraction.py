"""Scene contraction: all of space into the field's bounded cube (mip-NeRF 360, as nerfacto does).

A capture without masks shows everything around the object: walls, floor, a room. A field that
lives only in the object's box must paint all of that onto the box's walls, which no camera
sees from two sides alike. Contraction keeps the box itself linear and squeezes everything
outside it, out to infinity, into a shell around it (with the L-infinity norm, so the box stays
a box)::

    contract(x) = x                           if |x|_inf <= 1
                  (2 - 1 / |x|_inf) x / |x|_inf  otherwise          -> [-2, 2]^3

and then halves it, so the field and the occupancy grid see ``[-1, 1]^3`` as in a bounded
scene. Differentiable, so poses learn through it.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["contract"]


def contract(x: Tensor) -> Tensor:
    """Box coordinates [N, 3] (the region of interest is [-1, 1]^3) -> grid coordinates [N, 3] in [-1, 1]."""
    norm = x.abs().amax(-1, keepdim=True)  # [N, 1]
    outside = norm > 1
    safe = torch.where(outside, norm, torch.ones_like(norm))
    squeezed = (2 - 1 / safe) * (x / safe)
    return torch.where(outside, squeezed, x) * 0.5
