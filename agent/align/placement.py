"""Placing a keyframe's features in 3-D, in the robot's own frame: from a metric depth prior, or by
triangulating them against the robot's other views with its known local poses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.align.config import AlignConfig
from agent.align.features import OwnViews
from agent.align.keypoints import keypoint_rays, reprojection_error, triangulate_rays
from agent.camera import opencv_to_pixel, optical_axis

__all__ = ["place_keyframe_features"]


@dataclass
class _Keyframe:
    view: int
    xy: np.ndarray  # [N, 2] OpenCV keypoints
    desc: np.ndarray  # [N, 128] RootSIFT
    origin: np.ndarray  # [3] camera centre
    dirs: np.ndarray  # [N, 3] unit rays through the keypoints


def place_keyframe_features(own: OwnViews, key: int, use_depth: bool, cfg: AlignConfig, stats: dict
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """View ``key``'s features in 3-D -> (points [N, 3], placed [N] bool, views that saw each [N]).

    Depth first where ``use_depth`` (a measured depth ranks first: 1e3 views), triangulation for
    the rest. ``stats`` counts the points of each kind.
    """
    xy, desc, _ = own.features(key)
    origin, dirs = keypoint_rays(own.c2w[key], own.intr[key], xy)
    kf = _Keyframe(key, xy, desc, origin, dirs)
    n = len(xy)
    pts = np.zeros((n, 3))
    have = np.zeros(n, dtype=bool)
    nviews = np.zeros(n)
    if use_depth:
        z = _depth_lookup(own.depth[key], xy, cfg.depth_search_px)
        d_cam_z = -(dirs @ own.c2w[key, :3, :3])[:, 2]  # cos of the ray to the optical axis, > 0
        have = z > 0
        pts[have] = origin + dirs[have] * (z[have] / d_cam_z[have])[:, None]
        nviews[have] = 1e3
        stats["depth"] += int(have.sum())
    todo = ~have
    obs = _neighbour_observations(own, kf, todo, cfg)
    if obs is not None:
        x, tri, cnt = _triangulate(own, kf, todo, obs, cfg)
        pts[tri] = x[tri]
        have |= tri
        nviews[tri] = cnt[tri]
        stats["triangulated"] += int(tri.sum())
    return pts, have, nviews


def _depth_lookup(depth: np.ndarray, xy_cv: np.ndarray, radius: int) -> np.ndarray:
    """z-depth at keypoints [N, 2] -> [N] (0 = none): the valid pixel nearest to the keypoint."""
    h, w = depth.shape
    uv = opencv_to_pixel(xy_cv)
    ui = np.floor(uv[:, 0]).astype(int)  # pixel containing the continuous position
    vi = np.floor(uv[:, 1]).astype(int)
    best = np.zeros(len(xy_cv), dtype=np.float64)
    best_d = np.full(len(xy_cv), np.inf)
    for dv in range(-radius, radius + 1):
        for du in range(-radius, radius + 1):
            u, v = np.clip(ui + du, 0, w - 1), np.clip(vi + dv, 0, h - 1)
            z = depth[v, u]
            dist = du * du + dv * dv
            take = (z > 0) & (dist < best_d)
            best[take], best_d[take] = z[take], dist
    return best


def _neighbours(c2w: np.ndarray, key: int, cfg: AlignConfig) -> list[int]:
    """Own views to triangulate a keyframe with: similar direction, some parallax, a real baseline."""
    fwd = optical_axis(c2w)
    cos = np.clip(fwd @ fwd[key], -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    base = np.linalg.norm(c2w[:, :3, 3] - c2w[key, :3, 3], axis=1)
    scale = np.median(base[base > 0]) if (base > 0).any() else 1.0
    valid = (np.arange(len(c2w)) != key) & (angle <= cfg.neighbour_max_angle_deg) & (base > 1e-6 * scale)
    cand = np.flatnonzero(valid)
    order = cand[np.argsort(np.abs(angle[cand] - cfg.neighbour_angle_deg), kind="stable")]
    return [int(i) for i in order[: cfg.neighbours_per_keyframe]]


def _ratio_matches(own: OwnViews, kf: _Keyframe, j: int, todo: np.ndarray, cfg: AlignConfig
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Lowe ratio-test matches of the keyframe's unplaced features in view j: (keyframe idx, view j idx)."""
    xy_j, desc_j, _ = own.features(j)
    if len(xy_j) < 2:
        return None
    qi, ti = [], []
    for m in own.matcher.knnMatch(kf.desc, desc_j, k=2):
        if len(m) == 2 and m[0].distance < cfg.own_ratio * m[1].distance and todo[m[0].queryIdx]:
            qi.append(m[0].queryIdx)
            ti.append(m[0].trainIdx)
    return (np.array(qi), np.array(ti)) if qi else None


def _two_view_check(own: OwnViews, kf: _Keyframe, j: int, qi: np.ndarray, ti: np.ndarray,
                    origin_j: np.ndarray, dirs_j: np.ndarray, cfg: AlignConfig) -> np.ndarray:
    """[len(qi)] bool: the pair triangulates (known poses) and reprojects well in both views."""
    xy_j = own.features(j)[0]
    idx = np.repeat(np.arange(len(qi)), 2)
    ori = np.stack([np.broadcast_to(kf.origin, (len(qi), 3)), np.broadcast_to(origin_j, (len(qi), 3))], 1).reshape(-1, 3)
    dir_ = np.stack([kf.dirs[qi], dirs_j], 1).reshape(-1, 3)
    x2, ok2 = triangulate_rays(idx, ori, dir_, len(qi))
    err_k = reprojection_error(own.c2w[kf.view], own.intr[kf.view], x2, kf.xy[qi])
    err_j = reprojection_error(own.c2w[j], own.intr[j], x2, xy_j[ti])
    return ok2 & (err_k < cfg.max_reproj_px) & (err_j < cfg.max_reproj_px)


def _neighbour_observations(own: OwnViews, kf: _Keyframe, todo: np.ndarray, cfg: AlignConfig) -> tuple | None:
    """The neighbours' rays on the keyframe's unplaced features that pass the two-view check.

    -> (feature [O], origin [O, 3], direction [O, 3], view [O], OpenCV xy [O, 2]) or None.
    """
    obs_pt, obs_o, obs_d, obs_view, obs_xy = [], [], [], [], []
    for j in _neighbours(own.c2w, kf.view, cfg):
        matches = _ratio_matches(own, kf, j, todo, cfg)
        if matches is None:
            continue
        qi, ti = matches
        xy_j = own.features(j)[0]
        o_j, d_j = keypoint_rays(own.c2w[j], own.intr[j], xy_j[ti])
        good = _two_view_check(own, kf, j, qi, ti, o_j, d_j, cfg)
        for pos in np.flatnonzero(good):
            obs_pt.append(qi[pos])
            obs_o.append(own.c2w[j, :3, 3])
            obs_d.append(d_j[pos])
            obs_view.append(j)
            obs_xy.append(xy_j[ti[pos]])
    if not obs_pt:
        return None
    return np.array(obs_pt), np.array(obs_o), np.array(obs_d), np.array(obs_view), np.array(obs_xy)


def _triangulate(own: OwnViews, kf: _Keyframe, todo: np.ndarray, obs: tuple, cfg: AlignConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Multi-view solve of the keyframe's features -> (points [N, 3], accepted [N], rays per point [N]).

    Every observation must reproject; parallax: the widest angle between the point's rays.
    """
    obs_pt, obs_o, obs_d, obs_view, obs_xy = obs
    n = len(kf.xy)
    cand = np.unique(obs_pt)
    # Add the keyframe's own ray to every candidate's observation list.
    all_pt = np.concatenate([cand, obs_pt])
    all_o = np.concatenate([np.broadcast_to(kf.origin, (len(cand), 3)), obs_o])
    all_d = np.concatenate([kf.dirs[cand], obs_d])
    all_view = np.concatenate([np.full(len(cand), kf.view), obs_view])
    all_xy = np.concatenate([kf.xy[cand], obs_xy])
    x, ok = triangulate_rays(all_pt, all_o, all_d, n)
    bad = np.zeros(n, dtype=bool)
    for v in np.unique(all_view):
        sel = all_view == v
        e = reprojection_error(own.c2w[v], own.intr[v], x[all_pt[sel]], all_xy[sel])
        np.logical_or.at(bad, all_pt[sel], e >= cfg.max_reproj_px)
    min_cos = np.ones(n)
    np.minimum.at(min_cos, all_pt, np.einsum("ij,ij->i", all_d, kf.dirs[all_pt]))
    parallax_ok = np.degrees(np.arccos(np.clip(min_cos, -1, 1))) >= cfg.min_parallax_deg
    cnt = np.bincount(all_pt, minlength=n)
    return x, todo & ok & ~bad & parallax_ok & (cnt >= 2), cnt
