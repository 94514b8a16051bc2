"""A robot's relative pose to the shared frame: ``T_i``, learnt jointly with the field.

``T_i`` maps the robot's local frame into the shared frame g. Its learnt part is a correction
applied in the field's box (centred and unit-sized), so that rotation and translation decouple
and one learning rate suits every dataset. The reference robot freezes it (the gauge).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor, nn

from agent.config_io import check
from agent.geometry import sim3_from_params, sim3_inverse

__all__ = ["PoseConfig", "RelativePose"]


@dataclass
class PoseConfig:
    # fixed | se3 | sim3; None: what the swarm's frames call for (agent.frames); fixed for one robot
    mode: Literal["fixed", "se3", "sim3"] | None = None
    lr_rotation: float = 2e-3  # radians per step (Adam), about the box centre
    lr_translation: float = 2e-3  # box units per step
    lr_scale: float = 1e-3  # log-scale per step (sim3 only)
    start_step: int = 0  # the pose waits this many steps for the shared field to form
    decay_to: float = 0.1  # pose lr decays geometrically to this fraction at the end
    lr_factor_from_estimate: float = 0.1  # pose lrs x this from an estimate without a sigma: full Adam steps shake it loose
    travel_sigmas: float = 2.0  # from an estimate with a rotation sigma: the whole run moves the pose at most this many sigma

    def __post_init__(self) -> None:
        check(self, lr_rotation=">= 0", lr_translation=">= 0", lr_scale=">= 0", start_step=">= 0",
              decay_to="in (0, 1]", lr_factor_from_estimate=">= 0", travel_sigmas="> 0")

    def estimate_lr_scale(self, sigma_deg: float, arrived_step: int, total_steps: int) -> float:
        """Pose lrs x this from an estimate of rotation 1-sigma ``sigma_deg`` that arrived at
        ``arrived_step`` of ``total_steps``: the rest of the run moves it at most ``travel_sigmas`` sigma.

        What is left of the decayed schedule from that step is a geometric series; the rotation
        travels at most lr_rotation x its sum at 1x. A robot placed late (its path met a
        neighbour's only then) has the same travel in fewer, smaller steps."""
        if not math.isfinite(sigma_deg) or self.lr_rotation <= 0:
            return self.lr_factor_from_estimate
        span = max(total_steps - self.start_step, 1)
        first = min(max(arrived_step - self.start_step, 0), span - 1)  # steps of the schedule already gone
        ratio = self.decay_to ** (1.0 / span)
        left = span - first
        reach = float(left) if ratio >= 1.0 else ratio ** first * (1.0 - ratio ** left) / (1.0 - ratio)
        return min(1.0, self.travel_sigmas * math.radians(sigma_deg) / (self.lr_rotation * reach))


class RelativePose(nn.Module):
    """``T = B^-1 Exp(delta) B T0``: a correction ``delta`` applied in box coordinates.

    Working in the box (centred, unit-sized) decouples rotation from translation: a rotation
    turns the scene about its own centre instead of about the far-away origin of g, and the
    translation is in units of the scene size, so one learning rate suits every dataset.
    """

    def __init__(self, initial: Tensor, box_from_shared: Tensor, mode: str) -> None:
        super().__init__()
        self.mode = mode or "fixed"  # unset outside a swarm: a single robot has no relative pose
        self.register_buffer("base", initial.detach().to(torch.float32).clone())  # T0 [4, 4]
        self.register_buffer("box", box_from_shared.to(torch.float32).clone())  # B [4, 4]
        self.register_buffer("box_inv", sim3_inverse(box_from_shared.double()).float())
        self.phi = nn.Parameter(torch.zeros(3))
        self.translation = nn.Parameter(torch.zeros(3))
        self.log_scale = nn.Parameter(torch.zeros(()))
        self.from_estimate = False  # T0 came from an estimate (coarse alignment), not the identity
        self.estimate_sigma_deg = math.nan  # that estimate's rotation 1-sigma, when it stated one
        self.estimate_step = 0  # the training step the estimate arrived at
        self.set_trainable(self.mode != "fixed")

    def set_trainable(self, trainable: bool) -> None:
        self.phi.requires_grad_(trainable)
        self.translation.requires_grad_(trainable)
        self.log_scale.requires_grad_(trainable and self.mode == "sim3")

    @property
    def trainable(self) -> bool:
        return self.phi.requires_grad

    def matrix(self) -> Tensor:
        """T_shared_from_local: [4, 4] (differentiable in the correction).

        Written as ``T0 + B^-1 (Exp(delta) - I) B T0`` so that a zero correction gives T0 bit for
        bit: freezing (or a reference election) never nudges the pose by round-off.
        """
        delta = sim3_from_params(self.log_scale, self.phi, self.translation)
        eye = torch.eye(4, dtype=delta.dtype, device=delta.device)
        return self.base + self.box_inv @ (delta - eye) @ self.box @ self.base

    @torch.no_grad()
    def freeze(self) -> None:
        """Fold the current estimate into T0 and stop learning it (this robot became the reference).

        The frozen T is the current estimate, not the identity, so the shared frame stays put.
        """
        if any(bool(p.detach().abs().max() > 0) for p in (self.phi, self.translation, self.log_scale)):
            self.base.copy_(self.matrix())
        for p in (self.phi, self.translation, self.log_scale):
            p.zero_()
        self.set_trainable(False)

    @torch.no_grad()
    def set_box(self, box_from_shared: Tensor) -> None:
        """Adopt the swarm's field box (learnt at start by images-only robots); T is unchanged."""
        T = self.matrix()
        self.box.copy_(box_from_shared.to(self.box))
        self.box_inv.copy_(sim3_inverse(box_from_shared.double()).to(self.box_inv))
        self.base.copy_(T)
        for p in (self.phi, self.translation, self.log_scale):
            p.zero_()

    @torch.no_grad()
    def set_initial(self, transform: Tensor, sigma_deg: float = math.nan, step: int = 0) -> None:
        """Start from another estimate (e.g. the coarse keyframe alignment) with a zero correction.

        sigma_deg: the estimate's rotation 1-sigma, which bounds how fast the pose then learns;
        step: the training step it arrived at (a robot placed late has only the rest of the run).
        """
        self.base.copy_(transform.to(self.base))
        for p in (self.phi, self.translation, self.log_scale):
            p.zero_()
        self.from_estimate = True
        self.estimate_sigma_deg = float(sigma_deg)
        self.estimate_step = int(step)

    def unfreeze(self) -> None:
        """Learn again (a robot with a lower id came back and is the reference again)."""
        self.set_trainable(self.mode != "fixed")
