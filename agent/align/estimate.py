"""The pairwise estimate ``T_a_from_b``: match, RANSAC, decide against chance, refine in pixels."""

from __future__ import annotations

import math

import numpy as np

from agent.align.config import AlignConfig
from agent.align.matching import match_summaries, ransac_sim3
from agent.align.payload import AlignmentResult, Summary
from agent.align.refine import refine_by_reprojection
from agent.align.summary import summarise
from agent.data.views import Views

__all__ = ["estimate_relative", "initial_pose"]


def estimate_relative(summary_a: Summary, summary_b: Summary, cfg: AlignConfig = AlignConfig()) -> AlignmentResult:
    """``T_a_from_b`` from two summaries, or ``success=False`` with the reason it was rejected."""
    pairs = match_summaries(summary_a, summary_b, cfg)
    n = len(pairs)
    if n < max(cfg.min_inliers, 3):
        return AlignmentResult(None, 0, n, float("nan"), False,
                               f"only {n} descriptor matches (need {cfg.min_inliers}): no visible overlap")
    pa = summary_a.points[pairs[:, 0]].astype(np.float64)
    pb = summary_b.points[pairs[:, 1]].astype(np.float64)
    ra = summary_a.radius()
    thr = cfg.inlier_threshold * ra
    model, mask = ransac_sim3(pb, pa, thr, cfg)
    # Null hypothesis: the same search on matches with b shuffled (no true correspondence left).
    perm = np.random.default_rng(cfg.seed + 1).permutation(n)
    _, null_mask = ransac_sim3(pb[perm], pa, thr, cfg, seed=cfg.seed + 2)
    null_inl = int(null_mask.sum())
    if model is None:
        return AlignmentResult(None, 0, n, float("nan"), False, "RANSAC found no non-degenerate sample", null_inl)
    inl = int(mask.sum())
    res = pb[mask] @ model[:3, :3].T + model[:3, 3] - pa[mask]
    rmse = float(np.sqrt((res * res).sum(1).mean())) if inl else float("nan")
    scale = float(np.cbrt(abs(np.linalg.det(model[:3, :3]))))
    spread = float(np.linalg.svd(pa[mask] - pa[mask].mean(0), compute_uv=False)[1] / math.sqrt(inl)) if inl >= 3 else 0.0
    fail = None
    if inl < cfg.min_inliers:
        fail = f"{inl} inliers of {n} matches (need {cfg.min_inliers})"
    elif inl < cfg.min_inlier_ratio * n:
        fail = f"inlier ratio {inl / n:.3f} below {cfg.min_inlier_ratio}"
    elif inl < cfg.null_factor * null_inl:
        fail = f"{inl} inliers is not clearly above chance ({null_inl} on shuffled matches)"
    elif spread < cfg.min_spread * ra:
        fail = f"inliers nearly collinear (spread {spread:.3g} < {cfg.min_spread * ra:.3g})"
    elif not cfg.scale_range[0] <= scale <= cfg.scale_range[1]:
        fail = f"scale {scale:.3g} outside {cfg.scale_range}"
    if fail is not None:
        return AlignmentResult(None, inl, n, rmse, False, fail, null_inl, scale)
    reason = f"{inl} inliers of {n} matches (chance level {null_inl}), rmse {rmse:.3g}"
    sigma = float("nan")
    if cfg.reproj_refine and summary_a.has_cameras and summary_b.has_cameras:
        r2 = ((pb @ model[:3, :3].T + model[:3, 3] - pa) ** 2).sum(1)
        cand = pairs[r2 < (cfg.reproj_candidates * thr) ** 2]
        refined, note, sigma = refine_by_reprojection(model, summary_a, summary_b, cand, cfg)
        if refined is not None:
            model = refined
            scale = float(np.cbrt(abs(np.linalg.det(model[:3, :3]))))
        reason += f"; {note}"
    return AlignmentResult(model, inl, n, rmse, True, reason, null_inl, scale, sigma)


def initial_pose(own: Views | Summary, reference: Summary, cfg: AlignConfig = AlignConfig()
                 ) -> tuple[np.ndarray, AlignmentResult]:
    """The robot's starting ``T_i`` (= ``T_ref_from_own``, [4, 4] float64) from the reference's summary.

    Falls back to the identity (the paper's start) when the coarse step fails; the returned
    :class:`AlignmentResult` says which happened and why, for telemetry.
    """
    own_summary = own if isinstance(own, Summary) else summarise(own, "auto", cfg)
    res = estimate_relative(reference, own_summary, cfg)
    return (res.T_a_from_b.copy() if res.success else np.eye(4)), res
