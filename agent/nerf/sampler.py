"""Ray marching through the occupancy grid with early ray termination.

Samples are *packed*: one flat list of segments with the index of the ray each belongs to,
sorted by ray and then by distance (nerfacc's layout), so rays of very different sample counts
cost no padding.

Early termination without a custom kernel: the candidate samples in occupied cells are
evaluated without gradients in waves (the first few samples of every ray, then the next ones of
the rays still transparent, ...), and only samples in front of the point where the
transmittance falls below ``early_stop_eps`` are kept for the differentiable pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from agent.nerf.occupancy import OccupancyGrid


@dataclass
class MarchConfig:
    step_size: float = 2 * math.sqrt(3) / 128  # box units; ~a pixel footprint at 100x100 (finer for larger images)
    near: float = 0.0  # minimum distance from the camera, box units
    early_stop_eps: float = 1e-4  # stop a ray once its transmittance drops below this
    alpha_threshold: float = 0.0  # drop samples whose opacity is below this (0 = keep all)
    first_wave: int = 8  # samples per ray evaluated in the first visibility wave; later waves double
    skip_visibility_above: float = 0.6  # trainer: skip the visibility pass while it would keep more than this


@dataclass
class Samples:
    ray_index: Tensor  # [S] int64, non-decreasing
    t_mid: Tensor  # [S] distance of the segment centre along the ray (box units)
    dt: Tensor  # [S] segment length
    num_rays: int

    def __len__(self) -> int:
        return int(self.ray_index.shape[0])


def ray_box_intersection(origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test against [-1, 1]^3.  origins, directions: [R, 3] -> t_near, t_far: [R] (t_far < t_near: miss)."""
    inv = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
    t0 = (-1 - origins) * inv
    t1 = (1 - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


def segment_starts(ray_index: Tensor, num_rays: int) -> tuple[Tensor, Tensor]:
    """Per ray, the offset of its first sample and its sample count.  -> ([R], [R])."""
    counts = torch.bincount(ray_index, minlength=num_rays)
    starts = torch.cumsum(counts, 0) - counts
    return starts, counts


def exclusive_segment_cumsum(values: Tensor, ray_index: Tensor, num_rays: int) -> Tensor:
    """Within each ray, the sum of the values of the samples before each sample.  [S] -> [S].

    ``ray_index`` must be sorted. Accumulated in float64: the global running sum spans thousands
    of rays and would lose the small per-ray differences in float32.
    """
    if values.numel() == 0:
        return values
    v = values.double()
    exclusive = torch.cumsum(v, 0) - v  # global, across rays
    starts, _ = segment_starts(ray_index, num_rays)
    at_ray_start = exclusive[starts.clamp(max=v.numel() - 1)]  # [R] (rays without samples: unused)
    return (exclusive - at_ray_start[ray_index]).to(values.dtype)


@torch.no_grad()
def march(
    origins: Tensor,
    directions: Tensor,
    grid: OccupancyGrid,
    density_fn: Callable[[Tensor], Tensor],
    cfg: MarchConfig,
    jitter: Tensor | None = None,
    visibility: bool = True,
) -> Samples:
    """Candidate samples in occupied cells, thinned by early termination.

    origins, directions: [R, 3] in box coordinates (directions unit); jitter: [R] in [0, 1)
    (random offsets during training, None = 0.5 for evaluation); density_fn: x [N, 3] -> sigma [N].
    ``visibility=False`` skips the no-grad termination pass and returns every occupied candidate:
    cheaper while the field is still translucent and the pass would prune little.
    """
    num_rays = origins.shape[0]
    device = origins.device
    dt = cfg.step_size
    t_near, t_far = ray_box_intersection(origins, directions)
    t_near = t_near.clamp(min=cfg.near)
    steps = torch.ceil((t_far - t_near) / dt).clamp(min=0).to(torch.int64)  # [R]
    total = int(steps.sum())
    empty = Samples(torch.zeros(0, dtype=torch.int64, device=device), origins.new_zeros(0), origins.new_zeros(0),
                    num_rays)
    if total == 0:
        return empty
    ray_index = torch.repeat_interleave(torch.arange(num_rays, device=device), steps)  # [K0]
    first = torch.cumsum(steps, 0) - steps
    k = torch.arange(total, device=device) - first[ray_index]
    offset = 0.5 if jitter is None else jitter[ray_index]
    t_mid = t_near[ray_index] + (k + offset) * dt
    keep = t_mid < t_far[ray_index]
    x = origins[ray_index] + t_mid[:, None] * directions[ray_index]
    keep &= grid.is_occupied(x)
    ray_index, t_mid, x = ray_index[keep], t_mid[keep], x[keep]
    if ray_index.numel() == 0:
        return empty
    if not visibility:
        return Samples(ray_index, t_mid, torch.full_like(t_mid, dt), num_rays)

    # Visibility in waves: rank of each sample within its ray decides its wave.
    starts, _ = segment_starts(ray_index, num_rays)
    rank = torch.arange(ray_index.numel(), device=device) - starts[ray_index]
    optical_depth = torch.zeros(num_rays, device=device, dtype=torch.float64)  # accumulated sigma * dt
    keep = torch.zeros(ray_index.numel(), dtype=torch.bool, device=device)
    stop_depth = -math.log(cfg.early_stop_eps)
    lo, width = 0, cfg.first_wave
    max_rank = int(rank.max()) + 1
    while lo < max_rank:
        alive = optical_depth[ray_index] < stop_depth
        in_wave = (rank >= lo) & (rank < lo + width) & alive
        idx = in_wave.nonzero().squeeze(-1)
        if idx.numel() == 0:
            if not bool(alive.any()):
                break
            lo += width
            width *= 2
            continue
        sigma_dt = density_fn(x[idx]).double() * dt  # [W]
        before = optical_depth[ray_index[idx]] + exclusive_segment_cumsum(sigma_dt, ray_index[idx], num_rays)
        visible = before < stop_depth
        if cfg.alpha_threshold > 0:
            visible &= (1 - torch.exp(-sigma_dt)) >= cfg.alpha_threshold
        keep[idx[visible]] = True
        optical_depth.index_add_(0, ray_index[idx], sigma_dt)
        lo += width
        width *= 2
    return Samples(ray_index[keep], t_mid[keep], torch.full_like(t_mid[keep], dt), num_rays)
