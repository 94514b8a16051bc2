"""Volume rendering of colour, depth and opacity from packed samples, and whole-ray rendering.

``render_rays`` is the single entry point used by training and evaluation: it maps rays from the
shared frame into the field's box, marches them through the occupancy grid, evaluates the field
with gradients only on the samples that survive early termination, and composites.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from agent.nerf.field import NGPField
from agent.nerf.occupancy import OccupancyGrid
from agent.nerf.rays import Rays, transform_rays
from agent.nerf.sampler import MarchConfig, Samples, exclusive_segment_cumsum, march, segment_starts


@dataclass
class RenderOutput:
    rgb: Tensor  # [R, 3] composited onto the background
    depth: Tensor  # [R] z-depth in the rays' source frame, expected under the weights (0 where empty)
    opacity: Tensor  # [R] accumulated alpha
    num_samples: int  # samples evaluated with gradients
    num_visible: int  # of those, samples in front of early termination (transmittance > eps)
    weights: Tensor | None = None  # [S] each sample's compositing weight (for regularisers)
    samples: Samples | None = None  # the samples the weights belong to


def composite(sigma: Tensor, rgb: Tensor, samples: Samples) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Per-ray colour, expected distance and opacity, and each sample's transmittance and weight.

    sigma: [S], rgb: [S, 3] -> (rgb [R, 3], t [R], opacity [R], transmittance [S], weights [S])
    with ``w_k = T_k (1 - exp(-sigma_k dt_k))``, ``T_k = exp(-sum_{j<k} sigma_j dt_j)``.
    """
    r = samples.num_rays
    sigma_dt = sigma * samples.dt
    transmittance = torch.exp(-exclusive_segment_cumsum(sigma_dt, samples.ray_index, r))
    weights = transmittance * (1 - torch.exp(-sigma_dt))  # [S]
    idx = samples.ray_index
    color = torch.zeros(r, 3, dtype=rgb.dtype, device=rgb.device).index_add(0, idx, weights[:, None] * rgb)
    dist = torch.zeros(r, dtype=rgb.dtype, device=rgb.device).index_add(0, idx, weights * samples.t_mid)
    opacity = torch.zeros(r, dtype=rgb.dtype, device=rgb.device).index_add(0, idx, weights)
    return color, dist, opacity, transmittance, weights


def render_rays(
    field: NGPField,
    grid: OccupancyGrid,
    rays: Rays,
    background: Tensor,
    march_cfg: MarchConfig,
    box_from_frame: Tensor,
    jitter: Tensor | None = None,
    level_weights: Tensor | None = None,
    visibility: bool = True,
) -> RenderOutput:
    """Render rays given in some frame (shared frame ``g``) with the field living in its box.

    rays: R rays; background: [R, 3] or [3]; box_from_frame: [4, 4] similarity into [-1, 1]^3;
    jitter: [R] sample offsets in [0, 1) for training, None for deterministic evaluation.
    Gradients flow into the field and, through ``rays``, into any pose that produced them.
    """
    box_rays = transform_rays(rays, box_from_frame)
    # a field that models all of space maps box coordinates into its grid (contraction)
    to_grid = field.to_grid if getattr(field, "unbounded", False) else None

    def grid_of(x: Tensor) -> Tensor:
        return x if to_grid is None else to_grid(x)

    def density_fn(x: Tensor) -> Tensor:  # x: [N, 3] box coordinates
        return field.density(grid_of(x), level_weights)[0]

    samples = march(box_rays.origins.detach(), box_rays.directions.detach(), grid, density_fn, march_cfg, jitter,
                    visibility, to_grid=to_grid)
    idx = samples.ray_index
    x = box_rays.origins[idx] + samples.t_mid[:, None] * box_rays.directions[idx]  # [S, 3], differentiable
    sigma, rgb = field(grid_of(x), box_rays.directions[idx], level_weights)
    color, dist, opacity, transmittance, weights = composite(sigma, rgb, samples)
    bg = background.expand_as(color) if background.ndim == 1 else background
    color = color + (1 - opacity[:, None]) * bg
    visible = int((transmittance.detach() > march_cfg.early_stop_eps).sum())
    return RenderOutput(rgb=color, depth=dist * box_rays.z_per_t, opacity=opacity, num_samples=len(samples),
                        num_visible=visible, weights=weights, samples=samples)


@torch.no_grad()
def render_rays_eval(
    field: NGPField,
    grid: OccupancyGrid,
    rays: Rays,
    background: Tensor,
    march_cfg: MarchConfig,
    box_from_frame: Tensor,
    level_weights: Tensor | None = None,
) -> RenderOutput:
    """:func:`render_rays` for evaluation, with no gradient: each sample's field evaluated once.

    Training needs the visibility pass (a no-grad density pass that finds where each ray stops)
    before its differentiable one; without gradients both are one pass. The candidates in occupied
    cells are composited front to back in waves of ranks (``first_wave`` samples of every ray, then
    twice as many of the rays still transparent, ...), and a ray stops once its transmittance is
    below ``early_stop_eps``: the samples evaluated are those the training pass would keep, plus
    at most a wave's overshoot, and the result is the same composite."""
    box_rays = transform_rays(rays, box_from_frame)
    to_grid = field.to_grid if getattr(field, "unbounded", False) else None
    o, d = box_rays.origins, box_rays.directions
    samples = march(o, d, grid, lambda x: x, march_cfg, None, visibility=False, to_grid=to_grid)
    r = samples.num_rays
    color = torch.zeros(r, 3, dtype=o.dtype, device=o.device)
    dist, opacity = torch.zeros(r, dtype=o.dtype, device=o.device), torch.zeros(r, dtype=o.dtype, device=o.device)
    evaluated = 0
    if len(samples):
        idx_all = samples.ray_index
        starts, _ = segment_starts(idx_all, r)
        rank = torch.arange(len(samples), device=o.device) - starts[idx_all]
        depth_od = torch.zeros(r, dtype=torch.float64, device=o.device)  # optical depth so far, per ray
        stop = -math.log(march_cfg.early_stop_eps)
        lo, width, last = 0, march_cfg.first_wave, int(rank.max()) + 1
        while lo < last:
            pick = ((rank >= lo) & (rank < lo + width) & (depth_od[idx_all] < stop)).nonzero().squeeze(-1)
            lo, width = lo + width, width + width // 2  # slower growth than training's: every sample here is a full one
            if pick.numel() == 0:
                if not bool((depth_od < stop).any()):
                    break
                continue
            ri, t, dt = idx_all[pick], samples.t_mid[pick], samples.dt[pick]
            x = o[ri] + t[:, None] * d[ri]
            sigma, rgb = field(x if to_grid is None else to_grid(x), d[ri], level_weights)
            sigma_dt = (sigma * dt).double()
            before = depth_od[ri] + exclusive_segment_cumsum(sigma_dt, ri, r)
            w = (torch.exp(-before) * (1 - torch.exp(-sigma_dt))).to(o.dtype)  # [W] compositing weights
            if march_cfg.alpha_threshold > 0:
                w = w * ((1 - torch.exp(-sigma_dt)) >= march_cfg.alpha_threshold)
            color.index_add_(0, ri, w[:, None] * rgb)
            dist.index_add_(0, ri, w * t)
            opacity.index_add_(0, ri, w)
            depth_od.index_add_(0, ri, sigma_dt)
            evaluated += int(pick.numel())
    bg = background.expand_as(color) if background.ndim == 1 else background
    return RenderOutput(rgb=color + (1 - opacity[:, None]) * bg, depth=dist * box_rays.z_per_t, opacity=opacity,
                        num_samples=evaluated, num_visible=evaluated)


@torch.no_grad()
def render_image(
    field: NGPField,
    grid: OccupancyGrid,
    rays: Rays,
    width: int,
    height: int,
    background: Tensor,
    march_cfg: MarchConfig,
    box_from_frame: Tensor,
    chunk: int = 8192,
    level_weights: Tensor | None = None,
) -> dict[str, Tensor]:
    """Render a whole image in chunks.  -> rgb [H, W, 3], depth [H, W], opacity [H, W]."""
    parts = [render_rays_eval(field, grid, rays[i : i + chunk], background, march_cfg, box_from_frame, level_weights)
             for i in range(0, len(rays), chunk)]
    return {
        "rgb": torch.cat([p.rgb for p in parts]).reshape(height, width, 3),
        "depth": torch.cat([p.depth for p in parts]).reshape(height, width),
        "opacity": torch.cat([p.opacity for p in parts]).reshape(height, width),
    }
