"""Coarse initial relative pose between robots, without sharing images.

Joint NeRF + pose optimisation only converges from within roughly 45 deg / 1 m of the truth.
Robots with their own SfM start from arbitrary frames and scales, so this module gives the
optimisation a starting point from cheap geometry:

1. :func:`summarise`: each robot picks K keyframes spread over its views and keeps the SIFT
   features (RootSIFT, uint8) that it can place in 3-D in *its own* local frame: from a metric
   depth prior, or by triangulating against its other views with its known local poses. The
   payload (descriptors [P, 128] uint8, points [P, 3] float32, keyframe_index [P] int32,
   keypoints [P, 2] float32, keyframe_cameras [K, 16] float32) is a few hundred KB, far less
   than the images, and reveals no pixels.
2. :func:`estimate_relative`: a neighbour matches the descriptors (ratio test + mutual check,
   both aware that one 3-D point appears in several keyframes), fits a Sim(3) (or SE(3)) to the
   3-D/3-D matches by RANSAC over minimal Umeyama samples, refits on the inliers and decides.
   The decision compares the inlier count with what the same RANSAC finds on *shuffled*
   matches, so "no overlap" yields ``success=False`` with a reason instead of a wrong pose.
   The accepted estimate is then refined on the symmetric reprojection error of the matches
   (:func:`refine_by_reprojection`), which weighs each point as the keyframes saw it.
3. :func:`compose_along_graph`: pairwise estimates are chained from the reference robot along
   a best-inlier spanning tree, so robots that do not neighbour the reference get a start too.

Trainer usage (robot i, reference r)::

    s_i = summarise(views_i)                       # once, published to the neighbours
    res = estimate_relative(s_j, s_i)              # on neighbour j: T_j_from_i (or a reason)
    T = compose_along_graph(r, {(j, i): res, ...}).get(i)   # T_r_from_i = initial T_i, or None
    T, res = initial_pose(views_i, s_r)            # the one-hop case, identity if nothing found

Everything is numpy/OpenCV on the CPU and deterministic for ``AlignConfig.seed``.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
import torch

from agent.camera import camera_directions, opencv_to_pixel, optical_axis, pixel_to_opencv, project_points
from agent.data.views import Views
from agent.geometry import sim3_from_params, sim3_inverse, so3_exp, umeyama, umeyama_batched
from protocol.messages import KEYFRAME_CAMERA_DIM

__all__ = [
    "AlignConfig",
    "Summary",
    "AlignmentResult",
    "summarise",
    "estimate_relative",
    "compose_along_graph",
    "initial_pose",
    "match_summaries",
    "ransac_sim3",
    "refine_by_reprojection",
    "triangulate_rays",
]

SUMMARY_VERSION = 2  # 2: keypoints and keyframe cameras (for the reprojection refinement)
_DESC_DIM = 128
_BYTES_PER_POINT = _DESC_DIM + 3 * 4 + 4 + 2 * 4  # uint8 descriptor + float32 xyz + int32 keyframe + float32 uv


@dataclass(frozen=True)
class AlignConfig:
    """Settings of the summary and of the pairwise estimate; defaults run in seconds on 2 cores."""

    # --- summary (per robot) ---
    num_keyframes: int = 48  # K keyframes spread over the robot's views (all views if fewer): more
    # viewpoints match more of a neighbour's views; the byte budget still caps the payload
    max_bytes: int = 256_000  # cap on the payload: P <= max_bytes // 144
    sift_features: int = 2000  # SIFT detections per image
    sift_contrast: float = 0.02  # OpenCV contrastThreshold (lower = more features on flat CGI)
    neighbours_per_keyframe: int = 4  # own views matched to a keyframe to triangulate its features
    neighbour_angle_deg: float = 15.0  # preferred angle between keyframe and neighbour viewing directions
    neighbour_max_angle_deg: float = 50.0
    own_ratio: float = 0.8  # Lowe ratio for matches within the robot
    max_reproj_px: float = 2.0  # triangulated points must reproject this well in every view used
    min_parallax_deg: float = 2.0  # and be seen under at least this angle
    depth_search_px: int = 1  # "depth" source: look this far around a keypoint for a depth value
    depth_dense_fraction: float = 0.05  # "auto" uses depth only if this fraction of pixels has it
    descriptor_scale: float = 512.0  # RootSIFT -> uint8 quantisation factor
    # --- matching and RANSAC (pairwise) ---
    with_scale: bool = True  # Sim(3); False = SE(3) for robots that share a metric scale
    match_ratio: float = 0.85  # Lowe ratio against the best match of a *different* 3-D point
    dup_radius: float = 0.02  # same physical point if closer than this fraction of the scene radius
    ransac_iters: int = 3000
    inlier_threshold: float = 0.04  # fraction of the scene radius of the summary we map into
    min_sample_spread: float = 0.05  # minimal samples must span a triangle this wide (x radius)
    refine_iters: int = 5
    # Reprojection refinement (when both summaries carry keypoints and keyframe cameras): the 3-D
    # points' error lies mostly along their viewing rays (depth from a narrow baseline), which a
    # 3-D/3-D fit weighs as much as the lateral error. Measuring each match in pixels of the other
    # robot's keyframe weighs it as the cameras saw it, as ORB-SLAM's Sim(3) loop closure does.
    reproj_refine: bool = True
    reproj_candidates: float = 2.0  # matches within this x the 3-D inlier threshold take part
    reproj_scale_px: float = 1.0  # Cauchy loss scale, in pixels of the keyframes
    reproj_iters: int = 30  # Levenberg-Marquardt iterations
    reproj_max_change_deg: float = 5.0  # a refinement that turns the 3-D estimate more is refused
    seed: int = 0
    # --- decision ---
    min_inliers: int = 12
    min_inlier_ratio: float = 0.05
    null_factor: float = 2.0  # inliers must be >= this x the best count on shuffled matches
    min_spread: float = 0.1  # inliers' 2nd principal std must be >= this x the scene radius
    scale_range: tuple[float, float] = (1e-3, 1e3)


# --------------------------------------------------------------------------------------------
# Payload


@dataclass
class Summary:
    """What a robot publishes about its keyframes: descriptors and the 3-D points they see."""

    descriptors: np.ndarray  # [P, 128] uint8: RootSIFT * descriptor_scale
    points: np.ndarray  # [P, 3] float32, robot's local frame
    keyframe_index: np.ndarray  # [P] int32, which keyframe (0..K-1) saw the feature
    descriptor_scale: float = 512.0
    keypoints: np.ndarray | None = None  # [P, 2] float32: OpenCV pixel position in its keyframe
    keyframe_cameras: np.ndarray | None = None  # [K, 16] float32: c2w rows 0-2 (OpenGL) + fx, fy, cx, cy
    meta: dict = field(default_factory=dict)  # local statistics only; not part of the payload

    def __post_init__(self) -> None:
        p = self.points.shape[0]
        if self.descriptors.dtype != np.uint8 or self.descriptors.shape != (p, _DESC_DIM):
            raise ValueError(f"descriptors must be uint8 [{p}, {_DESC_DIM}], got {self.descriptors.dtype} "
                             f"{self.descriptors.shape}")
        if self.points.dtype != np.float32 or self.points.shape != (p, 3) or not np.isfinite(self.points).all():
            raise ValueError(f"points must be finite float32 [P, 3], got {self.points.dtype} {self.points.shape}")
        if self.keyframe_index.dtype != np.int32 or self.keyframe_index.shape != (p,):
            raise ValueError(f"keyframe_index must be int32 [{p}], got {self.keyframe_index.dtype} "
                             f"{self.keyframe_index.shape}")
        if not (self.descriptor_scale > 0 and math.isfinite(self.descriptor_scale)):
            raise ValueError(f"descriptor_scale must be positive, got {self.descriptor_scale}")
        if (self.keypoints is None) != (self.keyframe_cameras is None):
            raise ValueError("keypoints and keyframe_cameras come together (or neither)")
        if self.keypoints is not None:
            kp, cams = self.keypoints, self.keyframe_cameras
            if kp.dtype != np.float32 or kp.shape != (p, 2) or not np.isfinite(kp).all():
                raise ValueError(f"keypoints must be finite float32 [{p}, 2], got {kp.dtype} {kp.shape}")
            if cams.dtype != np.float32 or cams.ndim != 2 or cams.shape[1] != KEYFRAME_CAMERA_DIM or not np.isfinite(cams).all():
                raise ValueError(f"keyframe_cameras must be finite float32 [K, {KEYFRAME_CAMERA_DIM}], got {cams.dtype} {cams.shape}")
            if p and (self.keyframe_index.min() < 0 or self.keyframe_index.max() >= len(cams)):
                raise ValueError(f"keyframe_index outside the {len(cams)} keyframe cameras")
            if len(cams) and not (cams[:, 12:14] > 0).all():
                raise ValueError("keyframe focal lengths must be positive")

    @property
    def has_cameras(self) -> bool:
        return self.keypoints is not None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays that cross the network (before any compression)."""
        extra = self.keypoints.nbytes + self.keyframe_cameras.nbytes if self.has_cameras else 0
        return int(self.descriptors.nbytes + self.points.nbytes + self.keyframe_index.nbytes + extra)

    def radius(self) -> float:
        """Robust scene radius: median distance of the points to their per-axis median."""
        if len(self) == 0:
            return 0.0
        return float(np.median(np.linalg.norm(self.points - np.median(self.points, 0), axis=1)))

    def to_arrays(self) -> dict:
        """Plain payload for the protocol layer (numpy arrays and scalars only)."""
        out = {
            "version": SUMMARY_VERSION,
            "descriptor_scale": float(self.descriptor_scale),
            "descriptors": self.descriptors,
            "points": self.points,
            "keyframe_index": self.keyframe_index,
        }
        if self.has_cameras:
            out.update(keypoints=self.keypoints, keyframe_cameras=self.keyframe_cameras)
        return out

    @classmethod
    def from_arrays(cls, payload: Mapping) -> "Summary":
        """Inverse of :meth:`to_arrays`; validates everything (the payload came from another robot)."""
        if payload.get("version") not in (1, SUMMARY_VERSION):
            raise ValueError(f"summary version {payload.get('version')!r}, expected 1 or {SUMMARY_VERSION}")
        kp, cams = payload.get("keypoints"), payload.get("keyframe_cameras")
        return cls(
            descriptors=np.asarray(payload["descriptors"]),
            points=np.asarray(payload["points"]),
            keyframe_index=np.asarray(payload["keyframe_index"]),
            descriptor_scale=float(payload["descriptor_scale"]),
            keypoints=None if kp is None else np.asarray(kp),
            keyframe_cameras=None if cams is None else np.asarray(cams),
        )


@dataclass
class AlignmentResult:
    """Outcome of one pairwise estimate. ``T_a_from_b`` maps b's local points into a's frame."""

    T_a_from_b: np.ndarray | None  # [4, 4] float64 [sR | t], None when not successful
    inliers: int
    matches: int
    rmse: float  # of the inliers, in a's units (nan without a model)
    success: bool
    reason: str
    null_inliers: int = 0  # best inlier count of the same RANSAC on shuffled matches
    scale: float = float("nan")
    # 1-sigma of the rotation, from the reprojection refinement's information matrix (nan without
    # it): how far the joint optimisation may need to move the estimate (PoseConfig.travel_sigmas).
    rotation_sigma_deg: float = float("nan")


# --------------------------------------------------------------------------------------------
# Camera helpers: SIFT gives OpenCV keypoint coordinates, the rest is agent.camera's convention


def _grey_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """[H, W, 3|4] float in [0, 1] -> [H, W] uint8, RGBA composited on white as everywhere else."""
    img = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if img.shape[-1] == 4:
        img = img[..., :3] * img[..., 3:4] + (1.0 - img[..., 3:4])
    grey = img[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8)


def _rays(c2w: np.ndarray, intr: np.ndarray, xy_cv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV keypoint coordinates [N, 2] -> (origin [3], unit directions [N, 3]) in the local frame."""
    uv = opencv_to_pixel(xy_cv)
    d = camera_directions(intr, uv[:, 0], uv[:, 1]) @ c2w[:3, :3].T
    return c2w[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


def _project(c2w: np.ndarray, intr: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (OpenCV pixel coordinates [N, 2], z-depth [N]; <= 0 behind)."""
    cams = np.concatenate([c2w[:3, :4].reshape(12), intr]).astype(np.float64)  # [16]
    uv, z = _project_cams(torch.from_numpy(np.tile(cams, (len(pts), 1))), torch.from_numpy(np.asarray(pts, np.float64)))
    return uv.numpy(), z.numpy()


def _project_cams(cams: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point cameras [N, 16] (c2w rows 0-2 + fx fy cx cy), points [N, 3] -> (OpenCV uv [N, 2],
    z-depth [N]). In torch so that the reprojection refinement can differentiate it."""
    uv, z = project_points(cams[:, :12].reshape(-1, 3, 4), cams[:, 12:16], pts)
    return pixel_to_opencv(uv), z


def triangulate_rays(point_index: np.ndarray, origins: np.ndarray, dirs: np.ndarray, num_points: int
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Multi-view triangulation: for each point, the 3-D position nearest (least squares) to its rays.

    point_index: [O] which point each observation belongs to; origins, dirs: [O, 3] (unit dirs).
    Returns (points [num_points, 3], ok [num_points] bool: at least two non-parallel rays).
    Any number of views per point; the caller checks reprojection error and parallax.
    """
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [O, 3, 3]: I - d d^T
    a = np.zeros((num_points, 3, 3))
    b = np.zeros((num_points, 3))
    np.add.at(a, point_index, proj)
    np.add.at(b, point_index, (proj @ origins[:, :, None])[:, :, 0])
    ok = np.linalg.det(a) > 1e-9
    a[~ok] = np.eye(3)
    x = np.linalg.solve(a, b[:, :, None])[:, :, 0]
    return x, ok


# --------------------------------------------------------------------------------------------
# Summary


def _farthest_views(c2w: np.ndarray, k: int) -> list[int]:
    """K views spread over positions and viewing directions (farthest-point sampling, deterministic)."""
    centres = c2w[:, :3, 3]
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).mean()) or 1.0
    feats = np.concatenate([centres / spread, optical_axis(c2w)], 1)  # scale-free: [M, 6]
    first = int(np.argmin(np.linalg.norm(feats - feats.mean(0), axis=1)))
    chosen = [first]
    dist = np.linalg.norm(feats - feats[first], axis=1)
    while len(chosen) < min(k, len(c2w)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(feats - feats[nxt], axis=1))
    return sorted(chosen)


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


def _rootsift(desc: np.ndarray) -> np.ndarray:
    """OpenCV SIFT [N, 128] -> RootSIFT (L1-normalise, square root): Hellinger kernel as a dot product."""
    d = desc.astype(np.float32)
    d /= d.sum(1, keepdims=True) + 1e-7
    return np.sqrt(d)


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


def _choose_source(views: Views, points_source: str, cfg: AlignConfig) -> str:
    if points_source in ("depth", "triangulate"):
        return points_source
    if points_source != "auto":
        raise ValueError(f"points_source must be 'auto', 'depth' or 'triangulate', got {points_source!r}")
    # A depth prior is used directly only if it is metric in the robot's frame (not a depth with an
    # unknown per-image scale/shift) and dense enough to hit keypoints; else triangulate.
    if views.depth is None or not views.meta.get("depth_metric", False):
        return "triangulate"
    dense = float((views.depth > 0).float().mean()) >= cfg.depth_dense_fraction
    return "depth" if dense else "triangulate"


def summarise(views: Views, points_source: Literal["auto", "depth", "triangulate"] = "auto",
              cfg: AlignConfig = AlignConfig()) -> Summary:
    """Keyframe features of one robot with 3-D points in its local frame (see the module docstring).

    ``points_source``: "triangulate" uses the robot's own views and local poses; "depth" unprojects
    ``views.depth`` at the keypoint where present (triangulating the rest); "auto" uses depth only
    when ``views.meta["depth_metric"]`` is true and the prior is dense, since a depth prior with an
    unknown per-image scale/shift would put points in the wrong place.
    """
    source = _choose_source(views, points_source, cfg)
    c2w = views.c2w.detach().cpu().double().numpy()  # [M, 4, 4]
    intr = views.intrinsics.detach().cpu().double().numpy()  # [M, 4]
    depth = None if views.depth is None else views.depth.detach().cpu().numpy()  # [M, H, W]
    keys = _farthest_views(c2w, cfg.num_keyframes)
    sift = cv2.SIFT_create(nfeatures=cfg.sift_features, contrastThreshold=cfg.sift_contrast)
    feats: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # view -> (xy [N, 2], rootsift [N, 128], response [N])

    def features(i: int):
        if i not in feats:
            kps, desc = sift.detectAndCompute(_grey_uint8(views.images[i]), None)
            if desc is None or not kps:
                feats[i] = (np.zeros((0, 2)), np.zeros((0, _DESC_DIM), np.float32), np.zeros(0))
            else:
                feats[i] = (np.array([k.pt for k in kps], dtype=np.float64), _rootsift(desc),
                            np.array([k.response for k in kps]))
        return feats[i]

    matcher = cv2.BFMatcher(cv2.NORM_L2)
    out_desc, out_pts, out_kf, out_rank, out_xy = [], [], [], [], []
    stats = {"depth": 0, "triangulated": 0, "candidates": 0}
    for kf_slot, key in enumerate(keys):
        xy_k, desc_k, resp_k = features(key)
        n = len(xy_k)
        if n == 0:
            continue
        stats["candidates"] += n
        pts = np.zeros((n, 3))
        have = np.zeros(n, dtype=bool)
        nviews = np.zeros(n)
        if source == "depth" and depth is not None:
            z = _depth_lookup(depth[key], xy_k, cfg.depth_search_px)
            o, d = _rays(c2w[key], intr[key], xy_k)
            d_cam_z = -(d @ c2w[key, :3, :3])[:, 2]  # cos of the ray to the optical axis, > 0
            have = z > 0
            pts[have] = o + d[have] * (z[have] / d_cam_z[have])[:, None]
            nviews[have] = 1e3  # measured depth ranks first
            stats["depth"] += int(have.sum())
        # Triangulate what depth did not cover, from ratio-test matches with the neighbours.
        todo = ~have
        obs_pt, obs_o, obs_d, obs_view, obs_xy = [], [], [], [], []
        o_k, d_k = _rays(c2w[key], intr[key], xy_k)
        for j in _neighbours(c2w, key, cfg):
            xy_j, desc_j, _ = features(j)
            if len(xy_j) < 2:
                continue
            knn = matcher.knnMatch(desc_k, desc_j, k=2)
            qi, ti = [], []
            for m in knn:
                if len(m) == 2 and m[0].distance < cfg.own_ratio * m[1].distance and todo[m[0].queryIdx]:
                    qi.append(m[0].queryIdx)
                    ti.append(m[0].trainIdx)
            if not qi:
                continue
            qi, ti = np.array(qi), np.array(ti)
            # Two-view check with the known poses before the points join the multi-view solve.
            o_j, d_j = _rays(c2w[j], intr[j], xy_j[ti])
            idx = np.repeat(np.arange(len(qi)), 2)
            ori = np.stack([np.broadcast_to(o_k, (len(qi), 3)), np.broadcast_to(o_j, (len(qi), 3))], 1).reshape(-1, 3)
            dir_ = np.stack([d_k[qi], d_j], 1).reshape(-1, 3)
            x2, ok2 = triangulate_rays(idx, ori, dir_, len(qi))
            err_k = _reproj_err(c2w[key], intr[key], x2, xy_k[qi])
            err_j = _reproj_err(c2w[j], intr[j], x2, xy_j[ti])
            good = ok2 & (err_k < cfg.max_reproj_px) & (err_j < cfg.max_reproj_px)
            for pos in np.flatnonzero(good):
                obs_pt.append(qi[pos])
                obs_o.append(c2w[j, :3, 3])
                obs_d.append(d_j[pos])
                obs_view.append(j)
                obs_xy.append(xy_j[ti[pos]])
        if obs_pt:
            obs_pt = np.array(obs_pt)
            cand = np.unique(obs_pt)
            # Add the keyframe's own ray to every candidate's observation list.
            all_pt = np.concatenate([cand, obs_pt])
            all_o = np.concatenate([np.broadcast_to(o_k, (len(cand), 3)), np.array(obs_o)])
            all_d = np.concatenate([d_k[cand], np.array(obs_d)])
            all_view = np.concatenate([np.full(len(cand), key), np.array(obs_view)])
            all_xy = np.concatenate([xy_k[cand], np.array(obs_xy)])
            x, ok = triangulate_rays(all_pt, all_o, all_d, n)
            # Every observation must reproject; parallax: the widest angle between the point's rays.
            bad = np.zeros(n, dtype=bool)
            for v in np.unique(all_view):
                sel = all_view == v
                e = _reproj_err(c2w[v], intr[v], x[all_pt[sel]], all_xy[sel])
                np.logical_or.at(bad, all_pt[sel], e >= cfg.max_reproj_px)
            min_cos = np.ones(n)
            np.minimum.at(min_cos, all_pt, np.einsum("ij,ij->i", all_d, d_k[all_pt]))
            parallax_ok = np.degrees(np.arccos(np.clip(min_cos, -1, 1))) >= cfg.min_parallax_deg
            cnt = np.bincount(all_pt, minlength=n)
            tri = todo & ok & ~bad & parallax_ok & (cnt >= 2)
            pts[tri] = x[tri]
            have |= tri
            nviews[tri] = cnt[tri]
            stats["triangulated"] += int(tri.sum())
        sel = np.flatnonzero(have)
        out_desc.append(desc_k[sel])
        out_pts.append(pts[sel])
        out_kf.append(np.full(len(sel), kf_slot, dtype=np.int32))
        out_xy.append(xy_k[sel])
        out_rank.append(np.stack([nviews[sel], resp_k[sel]], 1))

    if out_desc:
        desc = np.concatenate(out_desc)
        pts = np.concatenate(out_pts)
        kf = np.concatenate(out_kf)
        rank = np.concatenate(out_rank)
        xy = np.concatenate(out_xy)
    else:
        desc, pts, kf, rank = np.zeros((0, _DESC_DIM), np.float32), np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros((0, 2))
        xy = np.zeros((0, 2))
    cameras = np.concatenate([c2w[keys, :3, :4].reshape(len(keys), 12), intr[keys]], 1).astype(np.float32)
    keep = _budget(kf, rank, max(cfg.max_bytes - cameras.nbytes, 0) // _BYTES_PER_POINT)
    quant = np.clip(np.rint(desc[keep] * cfg.descriptor_scale), 0, 255).astype(np.uint8)
    image_bytes = int(views.images.numel() * views.images.element_size())
    return Summary(
        descriptors=quant,
        points=pts[keep].astype(np.float32),
        keyframe_index=kf[keep].astype(np.int32),
        descriptor_scale=cfg.descriptor_scale,
        keypoints=xy[keep].astype(np.float32),
        keyframe_cameras=cameras,
        meta={"keyframes": [views.names[k] for k in keys], "points_source": source, **stats,
              "image_bytes_in_memory": image_bytes, "image_size": (views.width, views.height)},
    )


def _reproj_err(c2w: np.ndarray, intr: np.ndarray, pts: np.ndarray, xy_cv: np.ndarray) -> np.ndarray:
    """Pixel reprojection error [N]; infinite for points behind the camera."""
    uv, z = _project(c2w, intr, pts)
    err = np.linalg.norm(uv - xy_cv, axis=1)
    return np.where(z > 0, err, np.inf)


def _budget(kf: np.ndarray, rank: np.ndarray, max_points: int) -> np.ndarray:
    """Indices to keep: round-robin over keyframes, each in order of (views seen, SIFT response)."""
    if len(kf) <= max_points:
        return np.arange(len(kf))
    queues = []
    for k in np.unique(kf):
        idx = np.flatnonzero(kf == k)
        order = np.lexsort((-rank[idx, 1], -rank[idx, 0]))
        queues.append(idx[order])
    keep: list[int] = []
    depth = 0
    while len(keep) < max_points:
        for q in queues:
            if depth < len(q) and len(keep) < max_points:
                keep.append(int(q[depth]))
        depth += 1
    return np.sort(np.array(keep))


# --------------------------------------------------------------------------------------------
# Pairwise estimate


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
                          with_scale=cfg.with_scale).numpy()  # [B, 4, 4]
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
        model = umeyama(torch.from_numpy(src64[mask]), torch.from_numpy(dst64[mask]), with_scale=cfg.with_scale).numpy()
    r2 = ((src64 @ model[:3, :3].T + model[:3, 3] - dst64) ** 2).sum(1)
    return model, r2 < thr2


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
    f64 = torch.float64
    xa = torch.from_numpy(a.points[pairs[:, 0]].astype(np.float64))
    xb = torch.from_numpy(b.points[pairs[:, 1]].astype(np.float64))
    ua = torch.from_numpy(a.keypoints[pairs[:, 0]].astype(np.float64))
    ub = torch.from_numpy(b.keypoints[pairs[:, 1]].astype(np.float64))
    cam_a = torch.from_numpy(a.keyframe_cameras[a.keyframe_index[pairs[:, 0]]].astype(np.float64))
    cam_b = torch.from_numpy(b.keyframe_cameras[b.keyframe_index[pairs[:, 1]]].astype(np.float64))
    t0 = torch.from_numpy(model.astype(np.float64))
    c2 = cfg.reproj_scale_px ** 2

    def transform(xi: torch.Tensor) -> torch.Tensor:
        log_s = xi[6] if cfg.with_scale else torch.zeros((), dtype=f64)
        return t0 @ sim3_from_params(log_s, xi[:3], xi[3:6])

    def reproject(xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (residuals [4N]: a's image (u, v) then b's image (u, v), z-depths [2N])."""
        t = transform(xi)
        t_inv = sim3_inverse(t)
        uv_a, za = _project_cams(cam_a, xb @ t[:3, :3].T + t[:3, 3])
        uv_b, zb = _project_cams(cam_b, xa @ t_inv[:3, :3].T + t_inv[:3, 3])
        return torch.cat([uv_a - ua, uv_b - ub], 0).reshape(-1), torch.cat([za, zb])

    def residuals(xi: torch.Tensor) -> torch.Tensor:
        return reproject(xi)[0]

    def worse_view(r: torch.Tensor) -> torch.Tensor:  # [4N] -> [N]: the larger of a match's two errors
        return r.reshape(2, -1, 2).norm(dim=2).max(0).values

    def cost(r: torch.Tensor) -> float:
        return float(torch.log1p((r * r) / c2).sum())

    xi = torch.zeros(7, dtype=f64)
    r = residuals(xi)
    if not torch.isfinite(r).all():
        return None, "reprojection refinement skipped (points at a camera centre)", nan
    start_px = float(worse_view(r).median())
    lam, best = 1e-3, cost(r)
    for _ in range(cfg.reproj_iters):
        jac = torch.func.jacfwd(residuals)(xi)  # [4N, 7]: 7 forward passes
        if not cfg.with_scale:
            jac[:, 6] = 0
        w = 1.0 / (1.0 + r * r / c2)  # IRLS weights of the Cauchy loss
        jtj = jac.T @ (w[:, None] * jac)
        g = jac.T @ (w * r)
        improved = False
        for _ in range(10):
            step = torch.linalg.solve(jtj + lam * torch.diag(jtj.diagonal().clamp_min(1e-12)) + 1e-12 * torch.eye(7, dtype=f64), -g)
            r_new = residuals(xi + step)
            c_new = cost(r_new) if torch.isfinite(r_new).all() else math.inf
            if c_new < best:
                xi, r, best, lam, improved = xi + step, r_new, c_new, max(lam / 3, 1e-7), True
                break
            lam *= 4
        if not improved or float(step.abs().max()) < 1e-10:
            break
    _, z = reproject(xi)
    per_match = worse_view(r)
    in_front = (z.reshape(2, -1) > 0).all(0)
    good = int(((per_match < 3 * cfg.reproj_scale_px) & in_front).sum())
    turn = float(torch.rad2deg(so3_exp(xi[:3]).diagonal().sum().sub(1).div(2).clamp(-1, 1).acos()))
    if good < cfg.min_inliers:
        return None, f"reprojection refinement refused: {good} matches within {3 * cfg.reproj_scale_px:g} px", nan
    if turn > cfg.reproj_max_change_deg:
        return None, f"reprojection refinement refused: it turned the estimate by {turn:.1f} deg", nan
    end_px = float(per_match.median())
    sigma = _rotation_sigma_deg(torch.func.jacfwd(residuals)(xi), r, c2, cfg.with_scale)
    return transform(xi).numpy(), (f"refined on reprojection: {good} of {len(pairs)} matches within "
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


# --------------------------------------------------------------------------------------------
# Graph composition


def compose_along_graph(reference: Hashable, estimates: Mapping[tuple[Hashable, Hashable], np.ndarray | AlignmentResult | None]
                        ) -> dict[Hashable, np.ndarray]:
    """``T_ref_from_robot`` for every robot reachable from ``reference`` through the estimates.

    ``estimates[(a, b)]`` is ``T_a_from_b`` (a 4x4 array, or an :class:`AlignmentResult`, of which
    only the successful ones count). Edges are used in both directions. The chain follows a
    maximum spanning tree grown from the reference (Prim), weighted by inliers (plain arrays
    weigh 1), with ties broken by fewer hops: the most trusted path wins. Unreachable robots are
    absent from the result; the reference maps to the identity.
    """
    adj: dict[Hashable, list[tuple[float, Hashable, np.ndarray]]] = {}
    for (a, b), est in estimates.items():
        if est is None:
            continue
        if isinstance(est, AlignmentResult):
            if not est.success or est.T_a_from_b is None:
                continue
            t, w = np.asarray(est.T_a_from_b, dtype=np.float64), float(est.inliers)
        else:
            t, w = np.asarray(est, dtype=np.float64), 1.0
        if t.shape != (4, 4) or not np.isfinite(t).all():
            raise ValueError(f"estimate for {(a, b)} is not a finite 4x4 matrix")
        adj.setdefault(a, []).append((w, b, t))  # from a we can reach b: T_a_from_b
        adj.setdefault(b, []).append((w, a, _sim3_inv(t)))
    out = {reference: np.eye(4)}
    heap: list = []
    counter = 0

    def push(node: Hashable, hops: int) -> None:
        nonlocal counter
        for w, nxt, t in adj.get(node, []):
            if nxt not in out:
                heapq.heappush(heap, (-w, hops + 1, counter, node, nxt, t))
                counter += 1

    push(reference, 0)
    hops_of = {reference: 0}
    while heap:
        _, hops, _, src, dst, t = heapq.heappop(heap)
        if dst in out:
            continue
        out[dst] = out[src] @ t  # T_ref_from_dst = T_ref_from_src @ T_src_from_dst
        hops_of[dst] = hops
        push(dst, hops)
    return out


def initial_pose(own: Views | Summary, reference: Summary, cfg: AlignConfig = AlignConfig()
                 ) -> tuple[np.ndarray, AlignmentResult]:
    """The robot's starting ``T_i`` (= ``T_ref_from_own``, [4, 4] float64) from the reference's summary.

    Falls back to the identity (the paper's start) when the coarse step fails; the returned
    :class:`AlignmentResult` says which happened and why, for telemetry.
    """
    own_summary = own if isinstance(own, Summary) else summarise(own, "auto", cfg)
    res = estimate_relative(reference, own_summary, cfg)
    return (res.T_a_from_b.copy() if res.success else np.eye(4)), res


def _sim3_inv(t: np.ndarray) -> np.ndarray:
    return sim3_inverse(torch.from_numpy(t)).numpy()
