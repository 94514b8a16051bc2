"""Camera conventions of the whole project, said once: frames, pixels, projection, depth.

- Cameras are camera-to-world ``c2w`` 4x4 matrices in the OpenGL/Blender convention: +X right,
  +Y up in the image, the camera looks down -Z. OpenCV and COLMAP cameras (+Y down, looking
  down +Z) differ by a flip of the camera's Y and Z axes (:data:`OPENCV_FROM_OPENGL`). LLFF's
  ``poses_bounds.npy`` stores the camera axes in the order [down, right, back]
  (:func:`llff_to_opengl_c2w`).
- Intrinsics are ``[fx, fy, cx, cy]`` in pixels of the image they belong to.
- Pixel (column i, row j) covers ``[i, i + 1) x [j, j + 1)``: its centre is at ``(i + 0.5, j + 0.5)``
  (COLMAP's keypoints follow the same rule). OpenCV keypoints (SIFT) put the centre of pixel i at
  i, i.e. at our pixel coordinate minus 0.5.
- Depth is z-depth along the optical axis, 0 where unknown.
- Lens distortion is OpenCV's radial-tangential model (COLMAP's and nerfstudio's ``OPENCV``),
  coefficients ``(k1, k2, p1, p2)`` applied to normalised image coordinates ``((u - cx) / fx,
  (v - cy) / fy)`` with y *down* as in OpenCV (the tangential terms change sign with y). The
  0.5 pixel offset between OpenCV's pixel coordinates and ours cancels in these differences.

Functions that take pixel positions work on numpy arrays and torch tensors alike, so that the
numpy code (alignment, the procedural renderer) and the torch code (rays, depth) share one
formula and its float operations.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from agent.geometry import transform_points

__all__ = [
    "OPENCV_FROM_OPENGL",
    "PIXEL_CENTRE",
    "OPENCV_PIXEL_OFFSET",
    "opencv_to_opengl_c2w",
    "w2c_opencv_to_c2w_opengl",
    "llff_to_opengl_c2w",
    "opencv_camera_matrix",
    "intrinsics_from_opencv_matrix",
    "pixel_centre",
    "opencv_to_pixel",
    "pixel_to_opencv",
    "optical_axis",
    "camera_directions",
    "DISTORTION_KEYS",
    "distortion_coeffs",
    "distort",
    "undistort",
    "project_points",
    "focal_from_fov",
    "fov_from_focal",
    "unproject_depth",
]

# diag(1, -1, -1, 1): flips the camera's Y and Z axes; its own inverse, so it maps either way.
OPENCV_FROM_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
PIXEL_CENTRE = 0.5  # pixel i's centre sits at coordinate i + PIXEL_CENTRE
OPENCV_PIXEL_OFFSET = 0.5  # OpenCV keypoint coordinate = our pixel coordinate - this


def opencv_to_opengl_c2w(c2w_opencv: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world [..., 4, 4] -> OpenGL camera-to-world [..., 4, 4] (same centre)."""
    return c2w_opencv @ OPENCV_FROM_OPENGL


def w2c_opencv_to_c2w_opengl(w2c: np.ndarray) -> np.ndarray:
    """COLMAP's world-to-camera [4, 4] (OpenCV camera) -> OpenGL camera-to-world [4, 4]."""
    return opencv_to_opengl_c2w(np.linalg.inv(w2c))


def llff_to_opengl_c2w(poses: np.ndarray) -> np.ndarray:
    """LLFF camera-to-world [..., 3, 4+], columns [down, right, back | centre] -> OpenGL [..., 4, 4].

    OpenGL's [right, up, back] is LLFF's [col1, -col0, col2]; further columns (LLFF's H, W, focal) are dropped.
    """
    poses = np.asarray(poses, dtype=np.float64)
    c2w = np.zeros(poses.shape[:-2] + (4, 4))
    c2w[..., :3, 0] = poses[..., :3, 1]
    c2w[..., :3, 1] = -poses[..., :3, 0]
    c2w[..., :3, 2] = poses[..., :3, 2]
    c2w[..., :3, 3] = poses[..., :3, 3]
    c2w[..., 3, 3] = 1.0
    return c2w


def opencv_camera_matrix(intrinsics) -> np.ndarray:
    """(fx, fy, cx, cy) in this module's pixels -> OpenCV's 3x3 camera matrix (pixel i centred at i)."""
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    return np.array([[fx, 0.0, cx - OPENCV_PIXEL_OFFSET], [0.0, fy, cy - OPENCV_PIXEL_OFFSET], [0.0, 0.0, 1.0]])


def intrinsics_from_opencv_matrix(k: np.ndarray) -> tuple[float, float, float, float]:
    """Inverse of :func:`opencv_camera_matrix`: OpenCV's 3x3 camera matrix -> (fx, fy, cx, cy)."""
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]) + OPENCV_PIXEL_OFFSET, float(k[1, 2]) + OPENCV_PIXEL_OFFSET


def pixel_centre(index):
    """Pixel indices (int or float, numpy or torch) -> the coordinate of their centres."""
    return index + PIXEL_CENTRE


def opencv_to_pixel(xy_opencv):
    """OpenCV keypoint coordinates [..., 2] -> pixel coordinates of this module's convention."""
    return xy_opencv + OPENCV_PIXEL_OFFSET


def pixel_to_opencv(uv):
    """Pixel coordinates [..., 2] -> OpenCV keypoint coordinates."""
    return uv - OPENCV_PIXEL_OFFSET


def optical_axis(c2w):
    """The viewing direction (world frame) of cameras c2w: [..., 4, 4] -> [..., 3]: their -Z axis."""
    return -c2w[..., :3, 2]


def spread_views(c2w: np.ndarray, k: int) -> list[int]:
    """Of cameras c2w [M, 4, 4], the indices of K spread over positions and viewing directions
    (farthest-point sampling, deterministic; all M if fewer)."""
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


def camera_directions(intrinsics, u, v, distortion: tuple[float, float, float, float] | None = None):
    """Directions through pixel positions in the camera frame, scaled to z = -1 (not unit length).

    intrinsics: [..., 4] (fx, fy, cx, cy), u, v: pixel coordinates broadcastable with
    ``intrinsics[..., 0]`` -> [..., 3]. Image rows go down, camera +Y up. Since z = -1, a z-depth
    times the direction is the camera-frame point. ``distortion`` (k1, k2, p1, p2): the pixels
    are where a distorting lens put them, and the directions are the rays they came along.
    """
    fx, fy, cx, cy = (intrinsics[..., i] for i in range(4))
    x = (u - cx) / fx
    if distortion is None:
        y = -(v - cy) / fy
    else:
        x, y_down = undistort(x, (v - cy) / fy, distortion)
        y = -y_down
    if isinstance(x, Tensor):
        x, y = torch.broadcast_tensors(x, y)
        return torch.stack([x, y, -torch.ones_like(x)], -1)
    x, y = np.broadcast_arrays(x, y)
    return np.stack([x, y, -np.ones_like(x)], -1)


# nerfstudio's names of the OPENCV model's coefficients, in OpenCV's order (cv2's distCoeffs)
DISTORTION_KEYS = ("k1", "k2", "p1", "p2")


def distortion_coeffs(fields: dict | None) -> tuple[float, float, float, float] | None:
    """``{k1, k2, p1, p2}`` (missing keys are 0) -> the tuple, or None for a pinhole lens (all 0)."""
    coeffs = tuple(float((fields or {}).get(k, 0.0)) for k in DISTORTION_KEYS)
    return coeffs if any(coeffs) else None  # type: ignore[return-value]


def distort(x, y, coeffs: tuple[float, float, float, float]):
    """Where the lens moves normalised image points (OpenCV's, y down): (x, y) -> (x_d, y_d).

    x, y: numpy arrays or torch tensors of the same shape; coeffs: (k1, k2, p1, p2).
    """
    k1, k2, p1, p2 = coeffs
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort(x_d, y_d, coeffs: tuple[float, float, float, float], iterations: int = 10):
    """Inverse of :func:`distort` by Newton's method from (x_d, y_d): (x_d, y_d) -> (x, y).

    Converges quadratically wherever the lens is invertible (float64: ~1e-15 after a few steps
    for the distortions of real lenses); check with :func:`distort` when the lens is extreme.
    """
    k1, k2, p1, p2 = coeffs
    x, y = x_d, y_d
    for _ in range(iterations):
        ex, ey = distort(x, y, coeffs)
        ex, ey = ex - x_d, ey - y_d
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        dradial = 2 * (k1 + 2 * k2 * r2)  # d radial / dx = dradial * x, / dy = dradial * y
        # the Jacobian of distort, symmetric: d x_d / dy = d y_d / dx
        jxx = radial + dradial * x * x + 2 * p1 * y + 6 * p2 * x
        jxy = dradial * x * y + 2 * p1 * x + 2 * p2 * y
        jyy = radial + dradial * y * y + 6 * p1 * y + 2 * p2 * x
        det = jxx * jyy - jxy * jxy
        x, y = x - (jyy * ex - jxy * ey) / det, y - (jxx * ey - jxy * ex) / det
    return x, y


def project_points(c2w: Tensor, intrinsics: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole projection, one camera per point; differentiable (the alignment refines through it).

    c2w: [N, 3|4, 4], intrinsics: [N, 4], points: [N, 3] world -> (uv [N, 2] pixel coordinates,
    z-depth [N]; <= 0 behind the camera). A point at the camera centre's depth plane does not
    divide by zero (its depth is taken as 1e-12).
    """
    rot, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    cam = torch.einsum("nij,ni->nj", rot, points - centre)  # R^T (x - c)
    z = -cam[:, 2]
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    fx, fy, cx, cy = intrinsics.unbind(-1)
    u = fx * cam[:, 0] / zs + cx
    v = -fy * cam[:, 1] / zs + cy
    return torch.stack([u, v], 1), z


def focal_from_fov(size_px: float, fov_rad: float) -> float:
    """Focal length in pixels of an image ``size_px`` wide (or high) seeing ``fov_rad`` across it."""
    return 0.5 * size_px / math.tan(0.5 * fov_rad)


def fov_from_focal(size_px: float, focal: Tensor) -> Tensor:
    """Inverse of :func:`focal_from_fov`: the field of view in radians.  focal: [...] -> [...]."""
    return 2 * torch.atan(0.5 * size_px / focal)


def unproject_depth(depth: Tensor, intrinsics: Tensor, c2w: Tensor,
                    distortion: tuple[float, float, float, float] | None = None) -> Tensor:
    """The pixels with a known z-depth as 3-D points in the frame ``c2w`` maps into (ray through the pixel centre).

    depth: [H, W] (0 = unknown), intrinsics: [4], c2w: [4, 4] -> [N, 3] float64, row-major order.
    distortion: of the lens that recorded the depth map (see :func:`camera_directions`).
    """
    d = depth.to(torch.float64)
    rows, cols = torch.nonzero(d > 0, as_tuple=True)
    z = d[rows, cols]
    cam = camera_directions(intrinsics.to(torch.float64), pixel_centre(cols), pixel_centre(rows), distortion)
    cam = cam * z[:, None]  # [N, 3]
    return transform_points(c2w.to(torch.float64), cam)
