"""One robot's optimisation: field theta_i, relative pose T_i, depth scale/shift psi_i, C-ADMM.

The same class trains the centralised baseline (all views, pose fixed, no neighbours), a robot
alone, a robot of the in-process simulation and a robot inside the daemon: there is one
training loop in the project. Everything random comes from the trainer's own generator, so a
run is reproducible from its seeds whatever else runs in the process.

Frames: the robot's views are in its local frame; ``T_i`` (:class:`RelativePose`) maps them
into the shared frame g; ``box_from_shared`` maps g into the field's box [-1, 1]^3.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field as config_field
from typing import TYPE_CHECKING, Callable, Literal, Mapping

import torch
from torch import Tensor, nn

from agent.appearance import AppearanceConfig, ColourAffine
from agent.consensus import Consensus, ConsensusConfig
from agent.data.views import Views
from agent.geometry import sim3_decompose, sim3_inverse, so3_exp, transform_c2w
from agent.metrics import psnr, ssim
from agent.nerf.field import FieldConfig, NGPField
from agent.nerf.losses import distortion_loss
from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid
from agent.camera import pixel_centre
from agent.config_io import InvalidValue, check
from agent.nerf.rays import image_rays, pixel_rays
from agent.nerf.renderer import render_image, render_rays
from agent.nerf.sampler import MarchConfig
from agent.pose import PoseConfig, RelativePose

if TYPE_CHECKING:
    from agent.data.stream import ViewStream


@dataclass
class OptimConfig:
    lr: float = 1e-2
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-15
    warmup_steps: int = 50
    decay_at: tuple[float, ...] = (0.6, 0.85)  # fractions of total_steps where the lr is multiplied ...
    decay_factor: float = 0.33  # ... by this

    def __post_init__(self) -> None:
        check(self, lr="> 0", betas="in [0, 1)", eps="> 0", warmup_steps=">= 0", decay_at="in [0, 1]",
              decay_factor="> 0")


@dataclass
class CoarseToFineConfig:
    """BARF-style masking of the finer hash levels early on: widens the basin of the pose."""

    enabled: bool = False
    always_on_levels: int = 4
    start: float = 0.0  # fraction of total_steps where the finer levels begin to appear
    end: float = 0.5  # ... and where all of them are fully on

    def __post_init__(self) -> None:
        check(self, always_on_levels=">= 0", start="in [0, 1]", end="in [0, 1]")
        if self.end < self.start:
            raise InvalidValue("end", f"must be >= start ({self.start}), got {self.end!r}")


@dataclass
class CameraRefineConfig:
    """Refine the robot's own cameras while it trains (as BARF does): a small rotation about each
    camera's centre and a shift per view, and one focal-length scale for the robot.

    For robots whose cameras come from their own SfM: on lego they are 0.1-0.2 deg off the truth
    and the focal length differs, which a shared field cannot fit. The corrections stay on the
    robot (they are not part of theta) and start once the field has formed.
    """

    enabled: bool = False
    lr_rotation: float = 2e-4  # radians per step
    lr_translation: float = 2e-4  # box units per step
    lr_focal: float = 2e-4  # log focal length per step
    start_step: int = 200

    def __post_init__(self) -> None:
        check(self, lr_rotation=">= 0", lr_translation=">= 0", lr_focal=">= 0", start_step=">= 0")


@dataclass
class DepthConfig:
    # gamma, on the L1 depth error relative to the robot's median prior depth: an SfM prior is in
    # units of its own arbitrary scale, so a weight on the raw error would mean something else on
    # every robot. 0 disables the depth term.
    weight: float = 0.0
    learn_affine: bool = True  # learn a per-image scale a_m and shift b_m of the prior
    lr: float = 1e-3

    def __post_init__(self) -> None:
        check(self, weight=">= 0", lr=">= 0")


@dataclass
class TrainConfig:
    rays_per_step: int = 2048  # the most rays per step
    # Dynamic batch (nerfacc): aim at this many samples per step, so that early steps, when rays
    # are long and translucent, use fewer rays and cost about as much as later ones. 0 = off.
    target_samples_per_step: int = 0
    min_rays_per_step: int = 256
    total_steps: int = 2000  # for schedules; a swarm uses rounds * steps_per_round
    background: Literal["random", "white", "black"] = "random"
    seed: int = 0  # this robot's sampling seed
    init_seed: int = 0  # the field's initial weights: the same on every robot of a swarm
    device: str = "cpu"
    field: FieldConfig = config_field(default_factory=FieldConfig)
    occupancy: OccupancyConfig = config_field(default_factory=OccupancyConfig)
    march: MarchConfig = config_field(default_factory=MarchConfig)
    optim: OptimConfig = config_field(default_factory=OptimConfig)
    pose: PoseConfig = config_field(default_factory=PoseConfig)
    coarse_to_fine: CoarseToFineConfig = config_field(default_factory=CoarseToFineConfig)
    cameras: CameraRefineConfig = config_field(default_factory=CameraRefineConfig)
    depth: DepthConfig = config_field(default_factory=DepthConfig)
    appearance: AppearanceConfig = config_field(default_factory=AppearanceConfig)
    # Weight of the distortion loss (agent.nerf.losses): compact weights along each ray, against
    # floaters in front of far walls. Off by default: nerfacto's 0.002 cost the centralised room
    # model 8.6 dB, though it helped a weakly coupled swarm there (docs/results.md, the room).
    distortion: float = 0.0

    def __post_init__(self) -> None:
        check(self, distortion=">= 0", rays_per_step=">= 1", target_samples_per_step=">= 0",
              min_rays_per_step=">= 1", total_steps=">= 1", seed="in [0, 9.2e18)", init_seed="in [0, 9.2e18)")
        try:
            kind = torch.device(self.device).type
        except (RuntimeError, TypeError):
            raise InvalidValue("device", f"is not a torch device: {self.device!r}") from None
        available = {"cpu": True, "cuda": torch.cuda.is_available(), "mps": torch.backends.mps.is_available()}
        if not available.get(kind, False):
            raise InvalidValue("device", f"{self.device!r} is not available on this machine (available: "
                               f"{sorted(k for k, ok in available.items() if ok)})")


@dataclass
class StepStats:
    loss: float
    rgb_loss: float
    depth_loss: float
    batch_psnr: float
    samples_per_ray: float
    seconds: float
    steps: int


class RobotTrainer:
    """Trains one copy of the field on one robot's views (in its local frame)."""

    def __init__(
        self,
        views: Views,
        cfg: TrainConfig,
        box_from_shared: Tensor,
        initial_pose: Tensor | None = None,
        consensus: ConsensusConfig | None = None,
        rays: "ViewStream | None" = None,
        view_rows: int | None = None,
    ) -> None:
        """rays: the pixel source when views grow while training (agent.data.stream.ViewStream): per-view
        state is sized by ``rays.capacity``, ``views`` are the first. view_rows: per-view state for
        this many views (a stream run's checkpoint, loaded to render or evaluate)."""
        if cfg.field.unbounded is None:  # images that show their surroundings need all of space modelled
            cfg = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, unbounded=views.shows_surroundings))
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        dev = self.device
        self.views = views
        self.images = views.images.to(dev)  # [M, H, W, C]
        self.rays = rays
        m = rays.capacity if rays is not None else max(len(views), view_rows or 0)
        pad = m - len(views)  # rows of views still to come: filled by admit_views
        self.c2w_local = torch.cat([views.c2w, torch.eye(4).expand(pad, 4, 4)]).to(dev).float()  # [M, 4, 4]
        self.intrinsics = torch.cat([views.intrinsics, views.intrinsics[:1].expand(pad, 4)]).to(dev).float()  # [M, 4]
        self.depth_prior = None if views.depth is None else views.depth.to(dev)  # [M, H, W]
        known = None if self.depth_prior is None else self.depth_prior[self.depth_prior > 0]
        self.depth_unit = float(known.median()) if known is not None and known.numel() else 1.0  # local units
        self.box_from_shared = box_from_shared.to(dev).float()
        self.generator = torch.Generator(device=dev).manual_seed(cfg.seed)

        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.init_seed)  # every robot starts from the same theta^0
            self.field = NGPField(cfg.field).to(dev)
        self.grid = OccupancyGrid(cfg.occupancy, dev)
        initial = torch.eye(4) if initial_pose is None else initial_pose
        self.pose = RelativePose(initial, box_from_shared, cfg.pose.mode).to(dev)
        self.pose.from_estimate = initial_pose is not None
        self.depth_log_scale = nn.Parameter(torch.zeros(m, device=dev))  # log a_m
        self.depth_shift = nn.Parameter(torch.zeros(m, device=dev))  # b_m
        learn_affine = cfg.depth.weight > 0 and cfg.depth.learn_affine and self.depth_prior is not None
        self.depth_log_scale.requires_grad_(learn_affine)
        self.depth_shift.requires_grad_(learn_affine)
        refine = cfg.cameras.enabled
        self.view_phi = nn.Parameter(torch.zeros(m, 3, device=dev), requires_grad=refine)  # [M, 3]
        self.view_shift = nn.Parameter(torch.zeros(m, 3, device=dev), requires_grad=refine)  # [M, 3] box units
        # a calibrated camera (agent.data.sfm's camera file) keeps its focal length
        self.log_focal = nn.Parameter(torch.zeros((), device=dev),
                                      requires_grad=refine and not views.meta.get("focal_calibrated", False))

        self.appearance = ColourAffine(m, cfg.appearance, dev)  # per image, private (never in theta)
        o = cfg.optim
        self.theta_names = [n for n, _ in self.field.named_parameters()]
        self.optimizer = torch.optim.Adam(
            [
                {"params": list(self.field.parameters()), "lr": o.lr, "name": "field"},
                {"params": [self.pose.phi], "lr": cfg.pose.lr_rotation, "name": "rotation"},
                {"params": [self.pose.translation], "lr": cfg.pose.lr_translation, "name": "translation"},
                {"params": [self.pose.log_scale], "lr": cfg.pose.lr_scale, "name": "scale"},
                {"params": [self.depth_log_scale, self.depth_shift], "lr": cfg.depth.lr, "name": "depth"},
                {"params": [self.view_phi], "lr": cfg.cameras.lr_rotation, "name": "view_rotation"},
                {"params": [self.view_shift], "lr": cfg.cameras.lr_translation, "name": "view_shift"},
                {"params": [self.log_focal], "lr": cfg.cameras.lr_focal, "name": "focal"},
                {"params": [self.appearance.params], "lr": cfg.appearance.lr, "name": "appearance"},
            ],
            betas=o.betas,
            eps=o.eps,
        )
        self.base_lrs = [g["lr"] for g in self.optimizer.param_groups]
        self.consensus = Consensus(list(self.field.parameters()), consensus, self._rho_scales(consensus)) \
            if consensus else None
        self.step = 0
        # Running fraction of evaluated samples that early termination would keep. While it is
        # high (a young, translucent field) the no-grad visibility pass prunes little and is skipped.
        self.visible_fraction = 1.0
        self.samples_per_ray = 32.0  # running mean, drives the dynamic batch

    def set_box_from_shared(self, box_from_shared: Tensor) -> None:
        """Adopt the swarm's field box before training: robots with images only learn it from the
        reference (it lives in the reference's SfM frame), after this trainer was built."""
        if self.step != 0:
            raise RuntimeError("the field box can change only before the first step")
        self.box_from_shared = box_from_shared.to(self.device).float()
        self.pose.set_box(box_from_shared)

    # --- parameters exchanged with neighbours ---------------------------------------------
    def theta(self) -> dict[str, Tensor]:
        """A detached copy of theta_i (what is published)."""
        return {n: p.detach().clone() for n, p in self.field.named_parameters()}

    def _as_list(self, theta: Mapping[str, Tensor]) -> list[Tensor]:
        return [theta[n].to(self.device) for n in self.theta_names]

    @torch.no_grad()
    def load_theta(self, theta: Mapping[str, Tensor], reset_duals: bool = False) -> None:
        """Overwrite theta_i (a late joiner warm-starts from its neighbours; ``reset_duals`` when a
        model with a history is replaced, e.g. a robot back after rounds away)."""
        for n, p in self.field.named_parameters():
            p.copy_(theta[n])
        if reset_duals and self.consensus is not None:
            self.consensus.reset_duals()

    @torch.no_grad()
    def reset_occupancy(self) -> None:
        """Rebuild the occupancy grid from the current field (its theta was just replaced): the old
        grid pruned space by the field that is gone."""
        self.grid = OccupancyGrid(self.cfg.occupancy, self.device)
        lw = self.level_weights()
        self.grid.update(0, lambda x: self.field.density(x, lw)[0], self.generator)

    def begin_round(self, round_index: int, neighbours: Mapping[int, Mapping[str, Tensor]],
                    own: Mapping[str, Tensor] | None = None) -> None:
        """Anchors of round k from theta_i^k and the theta_j^k heard. ``own``: theta_i^k as the
        neighbours hold it (a lossy exchange), else the current parameters."""
        if self.consensus is None:
            return
        self.consensus.begin_round(round_index, self._own(own), {j: self._as_list(t) for j, t in neighbours.items()})

    def end_round(self, neighbours: Mapping[int, Mapping[str, Tensor]], own: Mapping[str, Tensor] | None = None,
                  rounds: Mapping[int, int] | None = None) -> None:
        """Dual update with theta_i^{k+1} (``own`` as in :meth:`begin_round`) and the theta_j^{k+1}
        heard (``rounds``: the round of each, when it may be a later one standing in)."""
        if self.consensus is None:
            return
        self.consensus.dual_update(self._own(own), {j: self._as_list(t) for j, t in neighbours.items()}, rounds)

    def _own(self, own: Mapping[str, Tensor] | None) -> list[Tensor]:
        return self._as_list(own) if own is not None else [p.detach() for p in self.field.parameters()]

    # --- schedules ---------------------------------------------------------------------------
    def _lr_factor(self, step: int) -> float:
        o = self.cfg.optim
        f = min(1.0, (step + 1) / max(o.warmup_steps, 1))
        for frac in o.decay_at:
            if step >= frac * self.cfg.total_steps:
                f *= o.decay_factor
        return f

    def _pose_lr_factor(self, step: int) -> float:
        return self.pose_lr_scale() * self._decayed_from(step, self.cfg.pose.start_step)

    def pose_lr_scale(self) -> float:
        """Pose lrs x this for the whole run: 1 from the identity, less from a (precise) estimate."""
        if not self.pose.from_estimate:
            return 1.0
        return self.cfg.pose.estimate_lr_scale(self.pose.estimate_sigma_deg, self.pose.estimate_step,
                                               self.cfg.total_steps)

    def _camera_lr_factor(self, step: int) -> float:
        return self._decayed_from(step, self.cfg.cameras.start_step) if self.cfg.cameras.enabled else 0.0

    def _decayed_from(self, step: int, start_step: int) -> float:
        """0 before ``start_step``, then down geometrically to ``pose.decay_to`` at the last step."""
        if step < start_step:
            return 0.0
        return self.cfg.pose.decay_to ** ((step - start_step) / max(self.cfg.total_steps - start_step, 1))

    def level_weights(self, step: int | None = None) -> Tensor | None:
        c = self.cfg.coarse_to_fine
        if not c.enabled:
            return None
        step = self.step if step is None else step
        levels = self.cfg.field.grid.num_levels
        span = max((c.end - c.start) * self.cfg.total_steps, 1.0)
        progress = min(max((step - c.start * self.cfg.total_steps) / span, 0.0), 1.0)
        alpha = progress * (levels - c.always_on_levels)
        k = torch.arange(levels, device=self.device, dtype=torch.float32) - c.always_on_levels
        w = (1 - torch.cos(math.pi * (alpha - k).clamp(0, 1))) / 2
        w[: c.always_on_levels] = 1.0
        return w

    # --- training ----------------------------------------------------------------------------
    def _background(self, n: int) -> Tensor:
        kind = self.cfg.background
        if kind == "random" and self.images.shape[-1] == 4:
            return torch.rand(n, 3, generator=self.generator, device=self.device)
        value = 0.0 if kind == "black" else 1.0
        return torch.full((n, 3), value, device=self.device)

    def cameras_shared(self) -> Tensor:
        """The robot's cameras in the shared frame g, refined.  -> [M, 4, 4] (differentiable in T
        and in the per-view corrections)."""
        c2w = transform_c2w(self.pose.matrix(), self.c2w_local)  # [M, 4, 4]
        if not self.cfg.cameras.enabled:
            return c2w
        box_scale = sim3_decompose(self.box_from_shared)[0]  # box units per shared unit
        rot = so3_exp(self.view_phi) @ c2w[:, :3, :3]  # [M, 3, 3] turned about the camera centre
        centre = c2w[:, :3, 3] + self.view_shift / box_scale  # [M, 3]
        top = torch.cat([rot, centre.unsqueeze(-1)], dim=-1)  # [M, 3, 4]
        return torch.cat([top, c2w[:, 3:, :]], dim=1)

    def camera_intrinsics(self) -> Tensor:
        """fx, fy, cx, cy of the robot's views with the learnt focal scale.  -> [M, 4]"""
        if not self.cfg.cameras.enabled:
            return self.intrinsics
        return torch.cat([self.intrinsics[:, :2] * torch.exp(self.log_focal), self.intrinsics[:, 2:]], dim=-1)

    @torch.no_grad()
    def refined_views(self) -> Views:
        """The robot's views with its refined cameras, back in its local frame (for calibration)."""
        if not self.cfg.cameras.enabled:
            return self.views
        v = self.views
        local = transform_c2w(sim3_inverse(self.pose.matrix().double()), self.cameras_shared()[:len(v)].double())
        return Views(v.images, local.float().cpu(), self.camera_intrinsics()[:len(v)].cpu(), list(v.names), v.depth,
                     v.meta)

    def _sample_pixels(self, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """n training pixels: view index, row, column [n] each, and their colour [n, C]."""
        if self.rays is not None:
            return self.rays.sample(n, self.generator, self.device)
        m, h, w, _ = self.images.shape
        img = torch.randint(0, m, (n,), generator=self.generator, device=self.device)
        px = torch.randint(0, h * w, (n,), generator=self.generator, device=self.device)
        row, col = px // w, px % w
        return img, row, col, self.images[img, row, col]

    @torch.no_grad()
    def admit_views(self, index: int, c2w: Tensor, intrinsics: Tensor, width: int, height: int) -> int:
        """A view that arrived while training takes row ``index`` (c2w [4, 4] local, intrinsics [4]);
        the occupancy grid opens where it is the first to look. Returns the cells opened."""
        self.c2w_local[index] = c2w.to(self.device).float()
        self.intrinsics[index] = intrinsics.to(self.device).float()
        c2w_box = self.box_from_shared @ transform_c2w(self.pose.matrix(), self.c2w_local[index:index + 1])[0]
        return self.grid.open_frustum(c2w_box, self.intrinsics[index], width, height, bool(self.cfg.field.unbounded),
                                      step=self.step, mark_only=self.step == 0)

    def train_step(self) -> dict[str, float]:
        cfg = self.cfg
        step = self.step
        lw = self.level_weights(step)
        self.grid.maybe_update(step, lambda x: self.field.density(x, lw)[0], self.generator)
        for group, base in zip(self.optimizer.param_groups, self.base_lrs):
            if group["name"] in ("rotation", "translation", "scale"):
                group["lr"] = base * self._pose_lr_factor(step)
            elif group["name"] in ("view_rotation", "view_shift", "focal"):
                group["lr"] = base * self._camera_lr_factor(step)
            elif group["name"] == "appearance":
                group["lr"] = base * self._lr_factor(step) * (step >= cfg.appearance.start_step)
            else:
                group["lr"] = base * self._lr_factor(step)

        n = cfg.rays_per_step
        if cfg.target_samples_per_step > 0:
            n = int(min(max(cfg.target_samples_per_step / max(self.samples_per_ray, 1e-3), cfg.min_rays_per_step), n))
        gen = self.generator
        img, row, col, pixels = self._sample_pixels(n)  # [n] each, pixels [n, C]
        c2w = self.cameras_shared()[img]  # [n, 4, 4]
        rays = pixel_rays(c2w, self.camera_intrinsics()[img], pixel_centre(col.float()), pixel_centre(row.float()))
        bg = self._background(n)
        if pixels.shape[-1] == 4:
            target = pixels[:, :3] * pixels[:, 3:] + (1 - pixels[:, 3:]) * bg
        else:
            target = pixels
        jitter = torch.rand(n, generator=gen, device=self.device)
        # Once the field is opaque enough for termination to pay, it stays on (fields only sharpen).
        use_visibility = self.visible_fraction < cfg.march.skip_visibility_above
        out = render_rays(self.field, self.grid, rays, bg, cfg.march, self.box_from_shared, jitter, lw,
                          visibility=use_visibility)
        if not use_visibility and out.num_samples:
            self.visible_fraction = 0.9 * self.visible_fraction + 0.1 * out.num_visible / out.num_samples
        self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * out.num_samples / n
        pred = out.rgb
        if cfg.appearance.enabled:
            pred = self.appearance.apply(self.appearance.params[img], out.rgb, out.opacity, bg)
        rgb_loss = ((pred - target) ** 2).mean()
        loss = rgb_loss + (self.appearance.penalty() if cfg.appearance.enabled else 0.0)
        if cfg.distortion and out.weights is not None:
            loss = loss + cfg.distortion * distortion_loss(out.weights, out.samples)
        depth_loss = torch.zeros((), device=self.device)
        if cfg.depth.weight > 0 and self.depth_prior is not None:
            prior = self.depth_prior[img, row, col]  # [n] local z-depth, 0 = none
            has = prior > 0
            if bool(has.any()):
                scale = sim3_decompose(self.pose.matrix())[0]  # s_i: local -> shared units
                rendered_local = out.depth / scale
                a = torch.exp(self.depth_log_scale[img])
                target_depth = a * prior + self.depth_shift[img]
                depth_loss = (rendered_local - target_depth).abs()[has].mean() / self.depth_unit
                loss = loss + cfg.depth.weight * depth_loss

        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.consensus is not None:
            self.consensus.add_penalty_grad(list(self.field.parameters()))
        self.optimizer.step()
        self.step += 1
        return {
            "loss": loss.item(),
            "rgb_loss": rgb_loss.item(),
            "depth_loss": depth_loss.item(),
            "samples": out.num_samples / n,
        }

    def _rho_scales(self, consensus: ConsensusConfig | None) -> list[float] | None:
        """Per field parameter: 1 for the hash table, ``mlp_rho_scale`` for the MLPs' weights."""
        if consensus is None:
            return None
        return [1.0 if name.startswith("encoding.") else consensus.mlp_rho_scale
                for name, _ in self.field.named_parameters()]

    def train(self, steps: int, on_step: Callable[[int], None] | None = None) -> StepStats:
        """Run ``steps`` optimiser steps; ``on_step`` is called after each (progress bars)."""
        t0 = time.perf_counter()
        sums = {"loss": 0.0, "rgb_loss": 0.0, "depth_loss": 0.0, "samples": 0.0}
        for i in range(steps):
            s = self.train_step()
            for k in sums:
                sums[k] += s[k]
            if on_step is not None:
                on_step(i + 1)
        k = max(steps, 1)
        mean_rgb = sums["rgb_loss"] / k
        return StepStats(
            loss=sums["loss"] / k,
            rgb_loss=mean_rgb,
            depth_loss=sums["depth_loss"] / k,
            batch_psnr=-10 * math.log10(max(mean_rgb, 1e-12)),
            samples_per_ray=sums["samples"] / k,
            seconds=time.perf_counter() - t0,
            steps=steps,
        )

    # --- rendering and evaluation -----------------------------------------------------------
    @torch.no_grad()
    def render(self, c2w_shared: Tensor, intrinsics: Tensor, width: int, height: int,
               background: float = 1.0, appearance: Tensor | None = None) -> dict[str, Tensor]:
        """Render a view given in the shared frame.  c2w_shared: [4, 4] -> rgb [H, W, 3], depth, opacity.

        appearance: [12], the colour transform to see it through (agent.appearance; None: the field's own)."""
        rays = image_rays(c2w_shared.to(self.device).float(), intrinsics.to(self.device).float(), width, height)
        bg = torch.full((3,), background, device=self.device)
        out = render_image(self.field, self.grid, rays, width, height, bg, self.cfg.march, self.box_from_shared,
                           level_weights=self.level_weights())
        if appearance is not None:
            n = width * height
            out["rgb"] = self.appearance.apply(appearance.to(self.device).expand(n, 12), out["rgb"].reshape(n, 3),
                                               out["opacity"].reshape(n), bg).reshape(height, width, 3)
        return out

    @torch.no_grad()
    def appearance_for(self, c2w_shared: Tensor) -> Tensor | None:
        """The colour transform of the training view nearest each camera.  [Q, 4, 4] -> [Q, 12] (None: off)."""
        if not self.cfg.appearance.enabled:
            return None
        return self.appearance.nearest(self.cameras_shared().detach(), c2w_shared.to(self.device).float())

    @torch.no_grad()
    def evaluate(self, views: Views, frame: Literal["local", "shared"] = "local", background: float = 1.0,
                 with_ssim: bool = True, appearance: Tensor | None = None,
                 renders: list | None = None) -> dict[str, list[float]]:
        """PSNR/SSIM on views given in this robot's local frame (via T_i) or already in frame g.

        appearance: [M, 12] per view (e.g. :meth:`appearance_for`); None: the field's own colour.
        renders: a list to append each view's render to ([H, W, 3] on the CPU), for who shows them."""
        c2w = views.c2w.to(self.device).float()
        if frame == "local":
            c2w = transform_c2w(self.pose.matrix(), c2w)
        gt = views.rgb(background).to(self.device)
        out: dict[str, list[float]] = {"psnr": [], "ssim": []}
        for i in range(len(views)):
            code = None if appearance is None else appearance[i]
            pred = self.render(c2w[i], views.intrinsics[i], views.width, views.height, background, code)["rgb"]
            out["psnr"].append(psnr(pred, gt[i]))
            if with_ssim:
                out["ssim"].append(ssim(pred, gt[i]))
            if renders is not None:
                renders.append(pred.cpu())
        return out

    @torch.no_grad()
    def own_views_psnr(self, every: int = 4) -> list[float]:
        """PSNR on every ``every``-th of the robot's own training views, through its refined cameras.

        How well the field fits what this robot saw. Alone, a robot fits its views whatever its
        cameras' errors, as long as they agree with each other; in a swarm the field must also
        agree with the others' cameras and live in the swarm's box. A low figure next to a robot
        alone says the shared field cannot hold this robot's views (on lego: a box that clipped
        the scene, see ``estimate_scene_box``).
        """
        sel = list(range(0, len(self.views), max(int(every), 1)))
        return self.evaluate(self.refined_views().subset(sel), with_ssim=False)["psnr"]

    # --- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "step": self.step,
            "field": self.field.state_dict(),
            "grid": self.grid.state_dict(),
            "pose": self.pose.state_dict(),
            "pose_trainable": self.pose.trainable,
            "pose_from_estimate": self.pose.from_estimate,
            "pose_estimate_sigma_deg": self.pose.estimate_sigma_deg,
            "pose_estimate_step": self.pose.estimate_step,
            "depth": {"log_scale": self.depth_log_scale.detach().clone(), "shift": self.depth_shift.detach().clone()},
            "appearance": self.appearance.params.detach().clone(),
            "cameras": {"phi": self.view_phi.detach().clone(), "shift": self.view_shift.detach().clone(),
                        "log_focal": self.log_focal.detach().clone()},
            "optimizer": self.optimizer.state_dict(),
            "consensus": None if self.consensus is None else self.consensus.state_dict(),
            "generator": self.generator.get_state(),
            "visible_fraction": self.visible_fraction,
            "samples_per_ray": self.samples_per_ray,
        }

    def load_state_dict(self, state: dict) -> None:
        self.step = int(state["step"])
        self.field.load_state_dict(state["field"])
        self.grid.load_state_dict(state["grid"])
        self.pose.load_state_dict(state["pose"])
        self.pose.set_trainable(bool(state["pose_trainable"]))
        self.pose.from_estimate = bool(state.get("pose_from_estimate", False))
        self.pose.estimate_sigma_deg = float(state.get("pose_estimate_sigma_deg", math.nan))
        self.pose.estimate_step = int(state.get("pose_estimate_step", 0))
        with torch.no_grad():
            self.depth_log_scale.copy_(state["depth"]["log_scale"])
            self.depth_shift.copy_(state["depth"]["shift"])
            if "cameras" in state:  # checkpoints from before camera refinement have none
                self.view_phi.copy_(state["cameras"]["phi"])
                self.view_shift.copy_(state["cameras"]["shift"])
                self.log_focal.copy_(state["cameras"]["log_focal"])
            if "appearance" in state:
                self.appearance.params.copy_(state["appearance"])
        opt = state["optimizer"]
        if len(opt["param_groups"]) < len(self.optimizer.param_groups):  # from before newer groups
            mine = self.optimizer.state_dict()["param_groups"]
            next_id = sum(len(g["params"]) for g in opt["param_groups"])
            extra = []
            for g in mine[len(opt["param_groups"]):]:
                extra.append({**g, "params": list(range(next_id, next_id + len(g["params"])))})
                next_id += len(g["params"])
            opt = {"state": opt["state"], "param_groups": opt["param_groups"] + extra}
        self.optimizer.load_state_dict(opt)
        if self.consensus is not None and state["consensus"] is not None:
            self.consensus.load_state_dict(state["consensus"])
        self.generator.set_state(state["generator"])
        self.visible_fraction = float(state["visible_fraction"])
        self.samples_per_ray = float(state["samples_per_ray"])
