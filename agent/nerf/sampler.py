"""Ray marching through the occupancy grid with early ray termination.

Samples are *packed*: one flat list of segments with the index of the ray each belongs to,
sorted by ray and then by distance (nerfacc's layout), so rays of very different sample counts
cost no padding.

Early termination without a custom kernel: the candidate samples in occupied cells are
evaluated without gradients in waves (the first few samples of every ray, then the next ones of
the rays still transparent, ...), and only samples in front of the point where the
transmittance falls below ``early_stop_eps`` are kept for the differentiable pass.

A bounded scene is marched through the box [-1, 1]^3 in steps of ``step_size``. An unbounded
one (a contracted field) is marched out to ``far``: uniform steps inside the box, and outside
it steps that grow with the distance, ``max(step_size, cone_angle * t)`` (instant-ngp's cone
stepping: about a pixel's footprint), so the far room costs a few hundred candidates per ray,
most of them skipped by the occupancy grid over the contracted cube.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from agent.config_io import InvalidValue, check
from agent.nerf.occupancy import OccupancyGrid


@dataclass
class MarchConfig:
    step_size: float = 2 * math.sqrt(3) / 128  # box units; ~a pixel footprint at 100x100 (finer for larger images)
    near: float = 0.0  # minimum distance from the camera, box units
    early_stop_eps: float = 1e-4  # stop a ray once its transmittance drops below this
    alpha_threshold: float = 0.0  # drop samples whose opacity is below this (0 = keep all)
    first_wave: int = 8  # samples per ray evaluated in the first visibility wave; later waves double
    skip_visibility_above: float = 0.6  # trainer: skip the visibility pass while it would keep more than this
    far: float = 1000.0  # unbounded fields: how far a ray is marched (box units)
    cone_angle: float = 1 / 32  # unbounded fields, outside the box: step = max(step_size, cone_angle * t)

    def __post_init__(self) -> None:
        check(self, step_size="> 0", near=">= 0", early_stop_eps="in (0, 1)", alpha_threshold="in [0, 1)",
              first_wave=">= 1", cone_angle=">= 0")
        if not self.far > self.near:
            raise InvalidValue("far", f"must be > near ({self.near}), got {self.far!r}")


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


def _uniform(t_near: Tensor, t_far: Tensor, dt: float, jitter: Tensor | None) -> tuple[Tensor, Tensor]:
    """Steps of ``dt`` through [t_near, t_far) per ray -> (ray_index [K], t_mid [K])."""
    ray_index, t_mid, _ = _uniform_ranked(t_near, t_far, dt, jitter)
    return ray_index, t_mid


def _uniform_ranked(t_near: Tensor, t_far: Tensor, dt: float, jitter: Tensor | None
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """As :func:`_uniform`, with each sample's rank within its ray ([K] int64)."""
    steps = torch.ceil((t_far - t_near) / dt).clamp(min=0).to(torch.int64)  # [R]
    total = int(steps.sum())
    ray_index = torch.repeat_interleave(torch.arange(t_near.shape[0], device=t_near.device), steps)  # [K]
    first = torch.cumsum(steps, 0) - steps
    k = torch.arange(total, device=t_near.device) - first[ray_index]
    offset = 0.5 if jitter is None else jitter[ray_index]
    t_mid = t_near[ray_index] + (k + offset) * dt
    keep = t_mid < t_far[ray_index]
    return ray_index[keep], t_mid[keep], k[keep]


def _cone(a: Tensor, b: Tensor, step: float, cone: float, jitter: Tensor | None
          ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Steps of ``max(step, cone * t)`` through [a, b) per ray -> (ray_index, t_mid, dt, rank in ray), each [K].

    Uniform below ``t_c = step / cone``, then geometric (``t_{k+1} = t_k (1 + cone)``), so the
    count per ray has a closed form and the samples stay packed without a loop over steps.
    """
    t_c = step / cone
    uni_end = torch.minimum(b, torch.full_like(b, t_c))
    n_uni = torch.ceil((uni_end - a) / step).clamp(min=0)  # [R]
    g_start = torch.maximum(a + n_uni * step, a).clamp(min=t_c)  # [R] first geometric edge
    ratio = 1.0 + cone
    n_geo = torch.ceil(torch.log(torch.clamp(b / g_start, min=1.0)) / torch.log(torch.tensor(ratio)))  # [R]
    counts = (n_uni + n_geo).to(torch.int64)
    ray_index = torch.repeat_interleave(torch.arange(a.shape[0], device=a.device), counts)
    first = torch.cumsum(counts, 0) - counts
    k = (torch.arange(int(counts.sum()), device=a.device) - first[ray_index]).to(a.dtype)
    j = torch.full_like(k, 0.5) if jitter is None else jitter[ray_index]
    nu = n_uni[ray_index]
    is_uni = k < nu
    g = (k - nu).clamp(min=0)
    edge = g_start[ray_index] * torch.pow(ratio, g)
    t_mid = torch.where(is_uni, a[ray_index] + (k + j) * step, edge * torch.pow(ratio, j))
    dt = torch.where(is_uni, torch.full_like(t_mid, step), edge * cone)
    keep = t_mid < b[ray_index]
    return ray_index[keep], t_mid[keep], dt[keep], k.to(torch.int64)[keep]


def _candidates_unbounded(origins: Tensor, directions: Tensor, cfg: MarchConfig,
                          jitter: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Before the box (cone steps), through it (uniform), after it out to ``far`` (cone steps)."""
    t_near, t_far = ray_box_intersection(origins, directions)
    hits = t_far > t_near
    near = torch.full_like(t_near, cfg.near)
    box_in = torch.where(hits, torch.maximum(t_near, near), near)
    box_out = torch.where(hits, torch.maximum(t_far, near), near)
    far = torch.full_like(t_near, cfg.far)
    parts = [_cone(near, box_in, cfg.step_size, cfg.cone_angle, jitter)]
    ri, tm, rank = _uniform_ranked(box_in, box_out, cfg.step_size, jitter)
    parts.append((ri, tm, torch.full_like(tm, cfg.step_size), rank))
    parts.append(_cone(box_out, far, cfg.step_size, cfg.cone_angle, jitter))
    # The three stretches follow each other along every ray: each sample's place in the packed
    # layout is its ray's start, the samples of the stretches before it on that ray, and its rank.
    num_rays = origins.shape[0]
    counts = torch.stack([torch.bincount(p[0], minlength=num_rays) for p in parts])  # [3, R]
    before = torch.cumsum(counts, 0) - counts  # [3, R] samples of the earlier stretches, per ray
    ray_start = torch.cumsum(counts.sum(0), 0) - counts.sum(0)  # [R]
    total = int(counts.sum())
    ray_index = torch.empty(total, dtype=torch.int64, device=origins.device)
    t_mid = torch.empty(total, dtype=origins.dtype, device=origins.device)
    dt = torch.empty(total, dtype=origins.dtype, device=origins.device)
    for part, (ri, tm, d, rank) in enumerate(parts):
        dest = ray_start[ri] + before[part][ri] + rank  # the ranks run 0.. within a stretch (candidates past b dropped last)
        ray_index[dest], t_mid[dest], dt[dest] = ri, tm, d
    return ray_index, t_mid, dt


@torch.no_grad()
def march(
    origins: Tensor,
    directions: Tensor,
    grid: OccupancyGrid,
    density_fn: Callable[[Tensor], Tensor],
    cfg: MarchConfig,
    jitter: Tensor | None = None,
    visibility: bool = True,
    to_grid: Callable[[Tensor], Tensor] | None = None,
) -> Samples:
    """Candidate samples in occupied cells, thinned by early termination.

    origins, directions: [R, 3] in box coordinates (directions unit); jitter: [R] in [0, 1)
    (random offsets during training, None = 0.5 for evaluation); density_fn: x [N, 3] (box
    coordinates) -> sigma [N]. ``to_grid``: the field's map from box to grid coordinates when it
    is unbounded (contracted), None for a bounded field. ``visibility=False`` skips the no-grad
    termination pass and returns every occupied candidate: cheaper while the field is still
    translucent and the pass would prune little.
    """
    num_rays = origins.shape[0]
    device = origins.device
    empty = Samples(torch.zeros(0, dtype=torch.int64, device=device), origins.new_zeros(0), origins.new_zeros(0),
                    num_rays)
    if to_grid is None:
        t_near, t_far = ray_box_intersection(origins, directions)
        ray_index, t_mid = _uniform(t_near.clamp(min=cfg.near), t_far, cfg.step_size, jitter)
        dt: float | Tensor = cfg.step_size
    else:
        ray_index, t_mid, dt = _candidates_unbounded(origins, directions, cfg, jitter)
    if ray_index.numel() == 0:
        return empty
    x = origins[ray_index] + t_mid[:, None] * directions[ray_index]
    keep = grid.is_occupied(x if to_grid is None else to_grid(x))
    ray_index, t_mid, x = ray_index[keep], t_mid[keep], x[keep]
    if isinstance(dt, Tensor):
        dt = dt[keep]
    if ray_index.numel() == 0:
        return empty
    dt_all = dt if isinstance(dt, Tensor) else torch.full_like(t_mid, dt)
    if not visibility:
        return Samples(ray_index, t_mid, dt_all, num_rays)
    keep = _visible(x, ray_index, dt, density_fn, cfg, num_rays)
    return Samples(ray_index[keep], t_mid[keep], dt_all[keep], num_rays)


def _visible(x: Tensor, ray_index: Tensor, dt: float | Tensor, density_fn: Callable[[Tensor], Tensor],
             cfg: MarchConfig, num_rays: int) -> Tensor:
    """Which candidates lie in front of early termination, evaluated in waves.  -> bool [S]."""
    device = x.device
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
        sigma_dt = density_fn(x[idx]).double() * (dt[idx].double() if isinstance(dt, Tensor) else dt)  # [W]
        before = optical_depth[ray_index[idx]] + exclusive_segment_cumsum(sigma_dt, ray_index[idx], num_rays)
        visible = before < stop_depth
        if cfg.alpha_threshold > 0:
            visible &= (1 - torch.exp(-sigma_dt)) >= cfg.alpha_threshold
        keep[idx[visible]] = True
        optical_depth.index_add_(0, ray_index[idx], sigma_dt)
        lo += width
        width *= 2
    return keep
