"""Putative 3-D/3-D matches between two summaries, and the RANSAC Sim(3) fit on them."""

from __future__ import annotations

import numpy as np
import torch

from agent.align.config import AlignConfig
from agent.align.payload import Summary
from agent.geometry import umeyama, umeyama_batched

__all__ = ["match_summaries", "ransac_sim3"]


def _unit_desc(s: Summary) -> np.ndarray:
    d = s.descriptors.astype(np.float32) / s.descriptor_scale
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-7)


def _one_way(dist: np.ndarray, pts_to: np.ndarray, dup_r: float, ratio: float, topk: int = 10
             ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest neighbour [N] and a ratio-test pass mask [N]; the runner-up must be a different 3-D point."""
    k = min(topk, dist.shape[1])
    part = np.argpartition(dist, k - 1, axis=1)[:, :k] if dist.shape[1] > k else np.tile(np.arange(k), (len(dist), 1))
    order = np.take_along_axis(part, np.argsort(np.take_along_axis(dist, part, 1), axis=1, kind="stable"), 1)
    best = order[:, 0]
    d_best = dist[np.arange(len(dist)), best]
    far = np.linalg.norm(pts_to[order] - pts_to[best][:, None], axis=2) > dup_r  # [N, k]
    far[:, 0] = False
    has = far.any(1)
    second = order[np.arange(len(dist)), np.argmax(far, 1)]
    d_second = dist[np.arange(len(dist)), second]
    ok = np.where(has, d_best < ratio * d_second, True)
    return best, ok


def match_summaries(a: Summary, b: Summary, cfg: AlignConfig = AlignConfig()) -> np.ndarray:
    """Putative 3-D/3-D matches [M, 2] (index in a, index in b): ratio test + mutual check, deduplicated.

    A physical point is in several keyframes, so the ratio test compares with the best match of
    a *different* point, the mutual check accepts any copy of the same point, and duplicate
    pairs (same point on both sides) are merged so that they do not inflate inlier counts.
    """
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    da, db = _unit_desc(a), _unit_desc(b)
    dist = np.sqrt(np.maximum(2.0 - 2.0 * (da @ db.T), 0.0))  # [Pa, Pb] L2 between unit vectors
    ra, rb = max(a.radius(), 1e-12), max(b.radius(), 1e-12)
    ab, ok_ab = _one_way(dist, b.points, cfg.dup_radius * rb, cfg.match_ratio)
    ba, ok_ba = _one_way(dist.T, a.points, cfg.dup_radius * ra, cfg.match_ratio)
    ia = np.arange(len(a))
    mutual = np.linalg.norm(a.points[ba[ab]] - a.points, axis=1) <= cfg.dup_radius * ra
    keep = ok_ab & ok_ba[ab] & mutual
    pairs = np.stack([ia[keep], ab[keep]], 1)
    order = np.argsort(dist[pairs[:, 0], pairs[:, 1]], kind="stable")
    pairs = pairs[order]
    kept: list[int] = []
    for m in range(len(pairs)):  # greedy merge of duplicates, best descriptor distance first
        if kept:
            prev = pairs[kept]
            same = (np.linalg.norm(a.points[prev[:, 0]] - a.points[pairs[m, 0]], axis=1) <= cfg.dup_radius * ra) & \
                   (np.linalg.norm(b.points[prev[:, 1]] - b.points[pairs[m, 1]], axis=1) <= cfg.dup_radius * rb)
            if same.any():
                continue
        kept.append(m)
    return pairs[kept] if kept else np.zeros((0, 2), dtype=np.int64)


def ransac_sim3(src: np.ndarray, dst: np.ndarray, threshold: float, cfg: AlignConfig = AlignConfig(),
                seed: int | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """RANSAC over minimal 3-point Umeyama samples for ``dst ~ s R src + t``, then refit on inliers.

    src, dst: [M, 3]; threshold: inlier distance in dst units. Returns (T [4, 4] float64 or None,
    inlier mask [M]). Samples whose triangles are too thin (in either set) or whose scale is
    outside ``cfg.scale_range`` are skipped. Deterministic for the seed.
    """
    m = len(src)
    mask = np.zeros(m, dtype=bool)
    if m < 3:
        return None, mask
    rng = np.random.default_rng(cfg.seed if seed is None else seed)
    src64, dst64 = src.astype(np.float64), dst.astype(np.float64)
    spread_src = float(np.median(np.linalg.norm(src64 - np.median(src64, 0), axis=1))) or 1.0
    spread_dst = float(np.median(np.linalg.norm(dst64 - np.median(dst64, 0), axis=1))) or 1.0
    samples = rng.integers(0, m, size=(cfg.ransac_iters, 3))
    samples = samples[(samples[:, 0] != samples[:, 1]) & (samples[:, 0] != samples[:, 2]) & (samples[:, 1] != samples[:, 2])]

    def area(p: np.ndarray) -> np.ndarray:  # [B, 3, 3] -> [B] twice the triangle area
        return np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)

    s_tri, d_tri = src64[samples], dst64[samples]
    wide = (area(s_tri) > (cfg.min_sample_spread * spread_src) ** 2) & (area(d_tri) > (cfg.min_sample_spread * spread_dst) ** 2)
    samples = samples[wide]
    if len(samples) == 0:
        return None, mask
    hyp = umeyama_batched(torch.from_numpy(src64[samples]), torch.from_numpy(dst64[samples]),
                          with_scale=cfg.sim3).numpy()  # [B, 4, 4]
    scale = np.cbrt(np.abs(np.linalg.det(hyp[:, :3, :3])))
    hyp = hyp[(scale >= cfg.scale_range[0]) & (scale <= cfg.scale_range[1])]
    if len(hyp) == 0:
        return None, mask
    thr2 = threshold * threshold
    best_cost, best = np.inf, None
    for start in range(0, len(hyp), 256):  # chunks bound the memory: [256, M, 3]
        h = hyp[start:start + 256]
        res = np.einsum("bij,mj->bmi", h[:, :3, :3], src64) + h[:, None, :3, 3] - dst64[None]
        cost = np.minimum((res * res).sum(-1), thr2).sum(1)  # MSAC: truncated squared residuals
        i = int(np.argmin(cost))
        if cost[i] < best_cost:
            best_cost, best = float(cost[i]), h[i]
    model = best
    for _ in range(cfg.refine_iters):  # local optimisation: refit on the inliers until stable
        r2 = ((src64 @ model[:3, :3].T + model[:3, 3] - dst64) ** 2).sum(1)
        new_mask = r2 < thr2
        if new_mask.sum() < 3:
            break
        if (new_mask == mask).all():
            break
        mask = new_mask
        model = umeyama(torch.from_numpy(src64[mask]), torch.from_numpy(dst64[mask]), with_scale=cfg.sim3).numpy()
    r2 = ((src64 @ model[:3, :3].T + model[:3, 3] - dst64) ** 2).sum(1)
    return model, r2 < thr2
