"""A robot's summary: keyframes spread over its views, their features and 3-D points, within a byte budget."""

from __future__ import annotations

from typing import Literal

import numpy as np

from agent.align.config import AlignConfig
from agent.align.features import OwnViews
from agent.align.keypoints import pack_keyframe_cameras
from agent.align.payload import BYTES_PER_POINT, DESC_DIM, Summary
from agent.align.placement import place_keyframe_features
from agent.camera import spread_views
from agent.data.views import Views

__all__ = ["summarise"]


def summarise(views: Views, points_source: Literal["auto", "depth", "triangulate"] = "auto",
              cfg: AlignConfig = AlignConfig()) -> Summary:
    """Keyframe features of one robot with 3-D points in its local frame (see :mod:`agent.align`).

    ``points_source``: "triangulate" uses the robot's own views and local poses; "depth" unprojects
    ``views.depth`` at the keypoint where present (triangulating the rest); "auto" uses depth only
    when ``views.meta["depth_metric"]`` is true and the prior is dense, since a depth prior with an
    unknown per-image scale/shift would put points in the wrong place.
    """
    source = _choose_source(views, points_source, cfg)
    own = OwnViews(views, cfg)
    keys = spread_views(own.c2w, cfg.num_keyframes)
    use_depth = source == "depth" and own.depth is not None
    stats = {"depth": 0, "triangulated": 0, "candidates": 0}
    parts = []  # per keyframe with features: (descriptors, points, keyframe slot, keypoints, rank)
    for kf_slot, key in enumerate(keys):
        xy_k, desc_k, resp_k = own.features(key)
        if len(xy_k) == 0:
            continue
        stats["candidates"] += len(xy_k)
        pts, have, nviews = place_keyframe_features(own, key, use_depth, cfg, stats)
        sel = np.flatnonzero(have)
        parts.append((desc_k[sel], pts[sel], np.full(len(sel), kf_slot, dtype=np.int32), xy_k[sel],
                      np.stack([nviews[sel], resp_k[sel]], 1)))
    return _within_budget(views, own, keys, parts, cfg,
                          meta={"keyframes": [views.names[k] for k in keys], "points_source": source, **stats})


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


def _within_budget(views: Views, own: OwnViews, keys: list[int], parts: list, cfg: AlignConfig, meta: dict) -> Summary:
    """The :class:`Summary` of the placed features, cut to ``cfg.max_bytes`` and quantised."""
    if parts:
        desc, pts, kf, xy, rank = (np.concatenate(column) for column in zip(*parts))
    else:
        desc, pts, kf, rank = np.zeros((0, DESC_DIM), np.float32), np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros((0, 2))
        xy = np.zeros((0, 2))
    cameras = pack_keyframe_cameras(own.c2w[keys], own.intr[keys]).astype(np.float32)
    keep = _budget(kf, rank, max(cfg.max_bytes - cameras.nbytes, 0) // BYTES_PER_POINT)
    quant = np.clip(np.rint(desc[keep] * cfg.descriptor_scale), 0, 255).astype(np.uint8)
    image_bytes = int(views.images.numel() * views.images.element_size())
    return Summary(
        descriptors=quant,
        points=pts[keep].astype(np.float32),
        keyframe_index=kf[keep].astype(np.int32),
        descriptor_scale=cfg.descriptor_scale,
        keypoints=xy[keep].astype(np.float32),
        keyframe_cameras=cameras,
        meta={**meta, "image_bytes_in_memory": image_bytes, "image_size": (views.width, views.height)},
    )


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
