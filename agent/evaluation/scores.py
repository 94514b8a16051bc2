"""A robot's field scored on the held-out views in the shared frame, and its pose against the truth.

A model trained on SfM cameras learns the scene as SfM saw it, so besides the plain scores on
the calibrated cameras (:func:`evaluate_robot`) the final model can also be scored with each
held-out view's pose fitted to its image (:func:`fit_view_pose`), as pose-free NeRF is evaluated.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch
from torch import Tensor

from agent.data.views import Views
from agent.evaluation.evalset import EvalSet
from agent.geometry import pose_error, sim3_inverse


@dataclass
class RobotEval:
    """Per-view scores of one robot's field (see :func:`evaluate_robot`)."""

    robot_id: int
    psnr: list[float]  # per held-out view
    ssim: list[float]
    others_only: list[int]  # indices of views only other robots saw
    pose: dict[str, float] = field(default_factory=dict)  # rotation_deg, translation, scale_rel
    psnr_pose_fitted: list[float] | None = None  # per held-out view, after fit_view_pose (if asked)
    psnr_true_intrinsics: list[float] | None = None  # per held-out view, with the truth's intrinsics (if asked)
    psnr_own_views: list[float] | None = None  # per own training view scored (if asked): the field's fit

    @staticmethod
    def _mean(values: list[float]) -> float:
        return sum(values) / len(values) if values else float("nan")

    @property
    def psnr_all(self) -> float:
        return self._mean(self.psnr)

    @property
    def ssim_all(self) -> float:
        return self._mean(self.ssim)

    @property
    def psnr_others(self) -> float:
        return self._mean([self.psnr[i] for i in self.others_only])

    @property
    def ssim_others(self) -> float:
        return self._mean([self.ssim[i] for i in self.others_only]) if self.ssim else float("nan")  # [] = not computed

    def summary(self) -> dict[str, float]:
        return {
            "psnr": self.psnr_all,
            "ssim": self.ssim_all,
            "psnr_others_only": self.psnr_others,
            "ssim_others_only": self.ssim_others,
            **({"psnr_pose_fitted": self._mean(self.psnr_pose_fitted)} if self.psnr_pose_fitted is not None else {}),
            **({"psnr_true_intrinsics": self._mean(self.psnr_true_intrinsics)}
               if self.psnr_true_intrinsics is not None else {}),
            **({"psnr_own_views": self._mean(self.psnr_own_views)} if self.psnr_own_views is not None else {}),
            **{f"pose_{k}": v for k, v in self.pose.items()},
        }


@dataclass
class ImageScores:
    """Mean PSNR/SSIM on all held-out views and on those only other robots saw (SSIM None: not computed)."""

    psnr: float
    ssim: float | None
    psnr_others_only: float
    ssim_others_only: float | None

    @classmethod
    def of(cls, ev: RobotEval, with_ssim: bool, **more):
        """The means of ``ev``; ``more``: the fields a subclass adds."""
        return cls(psnr=ev.psnr_all, ssim=ev.ssim_all if with_ssim else None, psnr_others_only=ev.psnr_others,
                   ssim_others_only=ev.ssim_others if with_ssim else None, **more)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def fit_view_pose(trainer, c2w: Tensor, intrinsics: Tensor, image: Tensor, steps: int,
                  rays_per_step: int = 2048, lr: float = 2e-3, seed: int = 0) -> Tensor:
    """A held-out camera's pose fitted to its image through the robot's frozen field.

    The test-time pose optimisation of pose-free NeRF evaluation (NeRF--, BARF): a model trained
    on SfM cameras learns the scene as SfM saw it (its focal length, its small pose errors), so a
    held-out view placed through a Sim(3) calibration is off by a fraction of a pixel, which PSNR
    punishes as if the field were wrong. Only the 6 pose numbers of this view move.

    c2w: [4, 4] in the shared frame; intrinsics: [4]; image: [H, W, 3] -> corrected c2w [4, 4].
    """
    from agent.geometry import sim3_from_params
    from agent.camera import pixel_centre
    from agent.nerf.rays import pixel_rays, transform_rays
    from agent.nerf.renderer import render_rays

    dev = trainer.device
    c2w = c2w.to(dev).float()
    k = intrinsics.to(dev).float()
    image = image.to(dev)
    height, width = image.shape[:2]
    phi = torch.zeros(3, device=dev, requires_grad=True)
    trans = torch.zeros(3, device=dev, requires_grad=True)
    opt = torch.optim.Adam([phi, trans], lr=lr)
    gen = torch.Generator(device=dev).manual_seed(seed)
    background = torch.ones(3, device=dev)
    zero = torch.zeros((), device=dev)
    c2w_inv = sim3_inverse(c2w.double()).float()  # pose math stays in agent.geometry
    for _ in range(steps):
        u = torch.randint(0, width, (rays_per_step,), generator=gen, device=dev)
        v = torch.randint(0, height, (rays_per_step,), generator=gen, device=dev)
        rays = pixel_rays(c2w.expand(rays_per_step, 4, 4), k.expand(rays_per_step, 4), pixel_centre(u), pixel_centre(v))
        moved = c2w @ sim3_from_params(zero, phi, trans) @ c2w_inv  # the correction, in camera coordinates
        out = render_rays(trainer.field, trainer.grid, transform_rays(rays, moved), background, trainer.cfg.march,
                          trainer.box_from_shared)
        loss = ((out.rgb - image[v, u]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return c2w @ sim3_from_params(zero, phi, trans)


def evaluate_robot(trainer, evalset: EvalSet, robot_id: int, with_ssim: bool = True,
                   pose_fit_steps: int = 0, compare_true_intrinsics: bool = False,
                   camera_of: int | None = None, own_views_every: int = 0) -> RobotEval:
    """Render every held-out view with this robot's field in the shared frame; compare to truth.

    The pose error is taken in the world frame (``T_world_from_shared @ T_i`` against
    ``T_world_from_local[i]``), so that the translation error is in scene units even when the
    shared frame has a scale of its own (an SfM frame). Rotation and relative scale are the same
    in either frame.
    """
    shared = Views(
        images=evalset.views.images,
        c2w=evalset.shared_cameras(),
        intrinsics=evalset.shared_intrinsics(camera_of),
        names=evalset.views.names,
    )
    # with per-image appearance, a held-out view is seen through the colour transform of the robot's
    # own training view nearest in pose (as NeRF-W scores unseen views); None: the field's own colour
    looks = trainer.appearance_for(shared.c2w)
    scores = trainer.evaluate(shared, frame="shared", with_ssim=with_ssim, appearance=looks)
    true_k = None
    if compare_true_intrinsics and not torch.equal(shared.intrinsics, evalset.views.intrinsics):
        as_truth = Views(images=shared.images, c2w=shared.c2w, intrinsics=evalset.views.intrinsics, names=shared.names)
        true_k = trainer.evaluate(as_truth, frame="shared", with_ssim=False, appearance=looks)["psnr"]
    fitted = None
    if pose_fit_steps > 0:
        gt = shared.rgb(1.0)  # [M, H, W, 3]
        cams = torch.stack([fit_view_pose(trainer, shared.c2w[m], shared.intrinsics[m], gt[m], pose_fit_steps, seed=m)
                            for m in range(len(shared))])
        moved = Views(images=shared.images, c2w=cams.cpu(), intrinsics=shared.intrinsics, names=shared.names)
        fitted = trainer.evaluate(moved, frame="shared", with_ssim=False, appearance=looks)["psnr"]
    own = trainer.own_views_psnr(own_views_every) if own_views_every > 0 else None
    estimate = trainer.pose.matrix().detach().double().cpu()
    return RobotEval(
        robot_id=robot_id,
        psnr=scores["psnr"],
        ssim=scores["ssim"],
        others_only=evalset.others_only(robot_id),
        pose=pose_error(evalset.world_from_local(evalset.reference_id) @ estimate, evalset.world_from_local(robot_id)),
        psnr_pose_fitted=fitted,
        psnr_true_intrinsics=true_k,
        psnr_own_views=own,
    )

