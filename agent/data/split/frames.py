"""Each robot's local frame (``T_world_from_local``) and depth prior."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from agent.data.split.config import SplitConfig
from agent.data.views import Views
from agent.geometry import random_rotation, so3_exp

__all__ = ["offset_transform", "local_frame", "depth_prior"]


def offset_transform(rotation_deg: tuple[float, float, float], translation: tuple[float, float, float]) -> Tensor:
    """``[R | t]`` with R = Rz(c) Ry(b) Rx(a) for rotation_deg = (a, b, c).  -> [4, 4] float64."""
    rot = torch.eye(3, dtype=torch.float64)
    for axis, deg in enumerate(rotation_deg):
        phi = torch.zeros(3, dtype=torch.float64)
        phi[axis] = math.radians(deg)
        rot = so3_exp(phi) @ rot
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot
    out[:3, 3] = torch.tensor(translation, dtype=torch.float64)
    return out


def depth_prior(cfg: SplitConfig, sub: Views, scale: float, gen: torch.Generator) -> tuple[Tensor, Tensor | None]:
    """The robot's depth prior [M_i, H, W] in its local units, and the affine [M_i, 2] of a "scaled" one."""
    assert sub.depth is not None
    depth = sub.depth.to(torch.float64) / scale
    affine = None
    if cfg.depth_prior == "scaled":
        a = torch.empty(len(sub), dtype=torch.float64).uniform_(*cfg.depth_scale_range, generator=gen)
        b = torch.empty(len(sub), dtype=torch.float64).uniform_(*cfg.depth_shift_range, generator=gen)
        affine = torch.stack([a, b], -1)
        known = depth > 0
        depth = torch.where(known, (a[:, None, None] * depth + b[:, None, None]).clamp_min(1e-6), 0.0)
    return depth.float(), affine


def local_frame(cfg: SplitConfig, is_reference: bool, sub: Views, gen: torch.Generator) -> Tensor:
    """T_world_from_local [4, 4] float64 of one robot."""
    if cfg.frame == "world":
        return torch.eye(4, dtype=torch.float64)
    if cfg.frame == "first_camera":
        return sub.c2w[0].to(torch.float64).clone()
    if cfg.frame == "offset":
        if is_reference:
            return torch.eye(4, dtype=torch.float64)
        return offset_transform(cfg.offset_rotation_deg, cfg.offset_translation)
    # random: rotation up to the max angle, translation uniform in the ball, optional scale
    out = torch.eye(4, dtype=torch.float64)
    rot = random_rotation(gen, cfg.random_max_angle_deg)
    direction = torch.randn(3, generator=gen, dtype=torch.float64)
    radius = cfg.random_max_translation * float(torch.rand((), generator=gen, dtype=torch.float64)) ** (1 / 3)
    log_s = math.log(cfg.random_max_scale)
    scale = math.exp((2 * float(torch.rand((), generator=gen, dtype=torch.float64)) - 1) * log_s) if log_s > 0 else 1.0
    out[:3, :3] = scale * rot
    out[:3, 3] = direction / direction.norm() * radius
    return out

