"""Keyframe geometry in OpenCV keypoint coordinates (what SIFT returns): rays, projection, triangulation.

Cameras are the numpy float64 c2w [4, 4] and intrinsics [4] of :mod:`agent.camera`; a summary
carries its keyframe cameras packed as [K, 16] (:func:`pack_keyframe_cameras`).
"""

from __future__ import annotations

import numpy as np
import torch

from agent.camera import camera_directions, opencv_to_pixel, pixel_to_opencv, project_points

__all__ = [
    "keypoint_rays",
    "pack_keyframe_cameras",
    "project_keyframe_cameras",
    "project_keypoints",
    "reprojection_error",
    "triangulate_rays",
]


def keypoint_rays(c2w: np.ndarray, intr: np.ndarray, xy_cv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV keypoint coordinates [N, 2] -> (origin [3], unit directions [N, 3]) in the local frame."""
    uv = opencv_to_pixel(xy_cv)
    d = camera_directions(intr, uv[:, 0], uv[:, 1]) @ c2w[:3, :3].T
    return c2w[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


def pack_keyframe_cameras(c2w: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """c2w [K, 4, 4] and intrinsics [K, 4] -> [K, 16]: c2w rows 0-2 (OpenGL), then fx, fy, cx, cy."""
    return np.concatenate([c2w[:, :3, :4].reshape(len(c2w), 12), intr], 1)


def project_keyframe_cameras(cams: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-point packed cameras [N, 16], points [N, 3] -> (OpenCV uv [N, 2], z-depth [N]).

    In torch so that the reprojection refinement can differentiate it.
    """
    uv, z = project_points(cams[:, :12].reshape(-1, 3, 4), cams[:, 12:16], pts)
    return pixel_to_opencv(uv), z


def project_keypoints(c2w: np.ndarray, intr: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] seen by one camera -> (OpenCV pixel coordinates [N, 2], z-depth [N]; <= 0 behind)."""
    cams = pack_keyframe_cameras(c2w[None], intr[None])[0].astype(np.float64)  # [16]
    uv, z = project_keyframe_cameras(torch.from_numpy(np.tile(cams, (len(pts), 1))),
                                     torch.from_numpy(np.asarray(pts, np.float64)))
    return uv.numpy(), z.numpy()


def reprojection_error(c2w: np.ndarray, intr: np.ndarray, pts: np.ndarray, xy_cv: np.ndarray) -> np.ndarray:
    """Pixel reprojection error [N]; infinite for points behind the camera."""
    uv, z = project_keypoints(c2w, intr, pts)
    err = np.linalg.norm(uv - xy_cv, axis=1)
    return np.where(z > 0, err, np.inf)


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
