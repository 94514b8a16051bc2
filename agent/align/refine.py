"""Refining an accepted 3-D/3-D estimate on the symmetric reprojection error of its matches.

The 3-D points' error lies mostly along their viewing rays (depth from a narrow baseline); in
pixels of the other robot's keyframes each match weighs as the cameras saw it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from agent.align.config import AlignConfig
from agent.align.keypoints import project_keyframe_cameras
from agent.align.payload import Summary
from agent.geometry import sim3_from_params, sim3_inverse, so3_exp

__all__ = ["refine_by_reprojection"]

_F64 = torch.float64


class _Reprojection:
    """Residuals of matched points as a function of a perturbation ``xi`` [7] of ``T_a_from_b``.

    ``xi`` = (rotation [3], translation [3], log scale); the scale stays 0 without ``with_scale``.
    """

    def __init__(self, model: np.ndarray, a: Summary, b: Summary, pairs: np.ndarray, with_scale: bool) -> None:
        self.xa = torch.from_numpy(a.points[pairs[:, 0]].astype(np.float64))  # [N, 3]
        self.xb = torch.from_numpy(b.points[pairs[:, 1]].astype(np.float64))
        self.ua = torch.from_numpy(a.keypoints[pairs[:, 0]].astype(np.float64))  # [N, 2] OpenCV
        self.ub = torch.from_numpy(b.keypoints[pairs[:, 1]].astype(np.float64))
        self.cam_a = torch.from_numpy(a.keyframe_cameras[a.keyframe_index[pairs[:, 0]]].astype(np.float64))  # [N, 16]
        self.cam_b = torch.from_numpy(b.keyframe_cameras[b.keyframe_index[pairs[:, 1]]].astype(np.float64))
        self.t0 = torch.from_numpy(model.astype(np.float64))
        self.with_scale = with_scale

    def transform(self, xi: torch.Tensor) -> torch.Tensor:
        log_s = xi[6] if self.with_scale else torch.zeros((), dtype=_F64)
        return self.t0 @ sim3_from_params(log_s, xi[:3], xi[3:6])

    def reproject(self, xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (residuals [4N]: a's image (u, v) then b's image (u, v), z-depths [2N])."""
        t = self.transform(xi)
        t_inv = sim3_inverse(t)
        uv_a, za = project_keyframe_cameras(self.cam_a, self.xb @ t[:3, :3].T + t[:3, 3])
        uv_b, zb = project_keyframe_cameras(self.cam_b, self.xa @ t_inv[:3, :3].T + t_inv[:3, 3])
        return torch.cat([uv_a - self.ua, uv_b - self.ub], 0).reshape(-1), torch.cat([za, zb])

    def residuals(self, xi: torch.Tensor) -> torch.Tensor:
        return self.reproject(xi)[0]


def _worse_view(r: torch.Tensor) -> torch.Tensor:
    """[4N] -> [N]: the larger of a match's two errors."""
    return r.reshape(2, -1, 2).norm(dim=2).max(0).values


def _cauchy_cost(r: torch.Tensor, c2: float) -> float:
    return float(torch.log1p((r * r) / c2).sum())


def _levenberg_marquardt(residuals: Callable[[torch.Tensor], torch.Tensor], xi: torch.Tensor, r: torch.Tensor,
                         c2: float, iters: int, with_scale: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimise the Cauchy loss of ``residuals`` from ``xi`` (with residuals ``r``) -> (xi, r)."""
    lam, best = 1e-3, _cauchy_cost(r, c2)
    for _ in range(iters):
        jac = torch.func.jacfwd(residuals)(xi)  # [4N, 7]: 7 forward passes
        if not with_scale:
            jac[:, 6] = 0
        w = 1.0 / (1.0 + r * r / c2)  # IRLS weights of the Cauchy loss
        jtj = jac.T @ (w[:, None] * jac)
        g = jac.T @ (w * r)
        improved = False
        for _ in range(10):
            step = torch.linalg.solve(jtj + lam * torch.diag(jtj.diagonal().clamp_min(1e-12)) + 1e-12 * torch.eye(7, dtype=_F64), -g)
            r_new = residuals(xi + step)
            c_new = _cauchy_cost(r_new, c2) if torch.isfinite(r_new).all() else math.inf
            if c_new < best:
                xi, r, best, lam, improved = xi + step, r_new, c_new, max(lam / 3, 1e-7), True
                break
            lam *= 4
        if not improved or float(step.abs().max()) < 1e-10:
            break
    return xi, r


def refine_by_reprojection(model: np.ndarray, a: Summary, b: Summary, pairs: np.ndarray,
                           cfg: AlignConfig = AlignConfig()) -> tuple[np.ndarray | None, str, float]:
    """Refine ``T_a_from_b`` on the symmetric reprojection error of matched points.

    For a match (point of a, point of b): b's point mapped by T must land on a's keypoint in a's
    keyframe, and a's point mapped by T^-1 on b's keypoint in b's keyframe. Levenberg-Marquardt
    on a Cauchy loss (pixels) over the 7 (or 6) parameters of a perturbation of T. Returns
    (T, note, rotation 1-sigma in degrees), or (None, why, nan) and leaves the estimate alone when
    there is too little to go on, the points fall behind the cameras, or the result turns away
    from the 3-D estimate by more than ``cfg.reproj_max_change_deg``.
    """
    nan = float("nan")
    if len(pairs) < max(cfg.min_inliers, 4):
        return None, f"reprojection refinement skipped ({len(pairs)} candidate matches)", nan
    problem = _Reprojection(model, a, b, pairs, cfg.sim3)
    c2 = cfg.reproj_scale_px ** 2
    xi = torch.zeros(7, dtype=_F64)
    r = problem.residuals(xi)
    if not torch.isfinite(r).all():
        return None, "reprojection refinement skipped (points at a camera centre)", nan
    start_px = float(_worse_view(r).median())
    xi, r = _levenberg_marquardt(problem.residuals, xi, r, c2, cfg.reproj_iters, cfg.sim3)
    _, z = problem.reproject(xi)
    per_match = _worse_view(r)
    in_front = (z.reshape(2, -1) > 0).all(0)
    good = int(((per_match < 3 * cfg.reproj_scale_px) & in_front).sum())
    turn = float(torch.rad2deg(so3_exp(xi[:3]).diagonal().sum().sub(1).div(2).clamp(-1, 1).acos()))
    if good < cfg.min_inliers:
        return None, f"reprojection refinement refused: {good} matches within {3 * cfg.reproj_scale_px:g} px", nan
    if turn > cfg.reproj_max_change_deg:
        return None, f"reprojection refinement refused: it turned the estimate by {turn:.1f} deg", nan
    end_px = float(per_match.median())
    sigma = _rotation_sigma_deg(torch.func.jacfwd(problem.residuals)(xi), r, c2, cfg.sim3)
    return problem.transform(xi).numpy(), (f"refined on reprojection: {good} of {len(pairs)} matches within "
                                           f"{3 * cfg.reproj_scale_px:g} px, median {start_px:.2f} -> {end_px:.2f} px, "
                                           f"rotation sigma {sigma:.3f} deg"), sigma


def _rotation_sigma_deg(jac: torch.Tensor, r: torch.Tensor, c2: float, with_scale: bool) -> float:
    """1-sigma of the rotation (norm of its 3 components) at a Cauchy least-squares optimum.

    jac: [R, 7], r: [R] residuals in pixels. Covariance s^2 (J^T W J)^-1 with the IRLS weights W
    and s^2 the weighted residual variance; each match counts once although it gives 4 residuals
    (its two points are not independent of the other robot's), so the result is not optimistic.
    """
    k = 7 if with_scale else 6
    jac = jac[:, :k]
    w = 1.0 / (1.0 + r * r / c2)
    s2 = float((w * r * r).sum() / max(float(w.sum()) - k, 1.0))
    info = jac.T @ (w[:, None] * jac) / 4.0
    try:
        cov = s2 * torch.linalg.inv(info)
    except RuntimeError:  # singular: the matches do not pin the rotation down
        return float("inf")
    return math.degrees(math.sqrt(max(float(cov[:3, :3].diagonal().sum()), 0.0)))
