"""Lens distortion: the models datasets declare, as OpenCV's two, undone when a dataset is loaded.

COLMAP and nerfstudio describe distortion in their own terms; every model supported here is one
of OpenCV's, acting on normalised camera coordinates ``(x, y) = (X / Z, Y / Z)``:

- radial-tangential, ``"radtan"`` (``cv2.undistort``): ``k1 k2 p1 p2 [k3 [k4 k5 k6]]``, the last
  three in the denominator of OpenCV's rational model (COLMAP FULL_OPENCV);
- fisheye, ``"fisheye"`` (``cv2.fisheye``): ``k1 k2 k3 k4`` on the angle from the optical axis
  (``k = 0`` is the equidistant fisheye, still far from a pinhole).

:class:`Undistortion` resamples an image onto the pinhole camera of the same size whose every
pixel has a source (no border to learn as black), so the rest of the project only sees pinholes.
It works at the file's native resolution, before any downscale, which is the resolution the
calibration belongs to.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, Literal

import cv2
import numpy as np

from agent.camera import intrinsics_from_opencv_matrix, opencv_camera_matrix, opencv_to_pixel, pixel_to_opencv
from agent.data.views import DataError

__all__ = ["Lens", "Undistortion", "colmap_lens", "transforms_lens", "ros_lens", "undistortion", "COLMAP_LENS_MODELS",
           "ROS_LENS_MODELS", "RADTAN_KEYS", "FISHEYE_KEYS"]

RADTAN_KEYS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # cv2's order of the coefficients
FISHEYE_KEYS = ("k1", "k2", "k3", "k4")

# COLMAP model -> (OpenCV model, where its extra parameters go among that model's coefficients)
COLMAP_LENS_MODELS: dict[str, tuple[str, tuple[int, ...]]] = {
    "SIMPLE_RADIAL": ("radtan", (0,)),  # f, cx, cy, k
    "RADIAL": ("radtan", (0, 1)),  # f, cx, cy, k1, k2
    "OPENCV": ("radtan", (0, 1, 2, 3)),  # fx, fy, cx, cy, k1, k2, p1, p2
    "FULL_OPENCV": ("radtan", (0, 1, 2, 3, 4, 5, 6, 7)),  # ..., k1, k2, p1, p2, k3, k4, k5, k6
    "SIMPLE_RADIAL_FISHEYE": ("fisheye", (0,)),  # f, cx, cy, k
    "RADIAL_FISHEYE": ("fisheye", (0, 1)),  # f, cx, cy, k1, k2
    "OPENCV_FISHEYE": ("fisheye", (0, 1, 2, 3)),  # fx, fy, cx, cy, k1, k2, k3, k4
    "SIMPLE_FISHEYE": ("fisheye", ()),  # f, cx, cy: equidistant
    "FISHEYE": ("fisheye", ()),  # fx, fy, cx, cy: equidistant
}


@dataclass(frozen=True)
class Lens:
    """A lens distortion in one of OpenCV's models; hashable, so that one map serves a whole camera."""

    model: Literal["radtan", "fisheye"]
    coeffs: tuple[float, ...]  # RADTAN_KEYS (4, 5 or 8 of them) or FISHEYE_KEYS, in that order
    name: str  # as the dataset names it: "COLMAP OPENCV", "nerfstudio OPENCV_FISHEYE", ...

    def describe(self) -> str:
        keys = RADTAN_KEYS if self.model == "radtan" else FISHEYE_KEYS
        values = ", ".join(f"{k} {v:.4g}" for k, v in zip(keys, self.coeffs) if v)
        return f"{self.name} ({values or 'no coefficients'})"


def colmap_lens(model_name: str, extra_params: list[float]) -> Lens | None:
    """The lens of a COLMAP camera model from its extra (non-pinhole) parameters; None for a pinhole."""
    if model_name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return None
    kind, slots = COLMAP_LENS_MODELS[model_name]
    coeffs = [0.0] * (4 if kind == "fisheye" else max(4, len(slots)))
    for slot, value in zip(slots, extra_params):
        coeffs[slot] = float(value)
    return _lens(kind, coeffs, f"COLMAP {model_name}")


def transforms_lens(camera_model: str, get: Callable[[str], float | None], fisheye: bool, where: str) -> Lens | None:
    """The lens of a transforms.json frame; ``get(key)`` reads a coefficient (the frame's, else the file's).

    nerfstudio's OPENCV has ``k1 k2 p1 p2`` (and ``k3``), its OPENCV_FISHEYE ``k1 .. k4``;
    instant-ngp writes the same keys without a camera_model (``is_fisheye`` for the fisheye).
    """
    values = {k: get(k) or 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if camera_model == "OPENCV_FISHEYE" or fisheye:
        if values["p1"] or values["p2"]:
            raise DataError(f"{where}: p1/p2 are not part of the OPENCV_FISHEYE model (k1 .. k4)")
        return _lens("fisheye", [values[k] for k in FISHEYE_KEYS], f"{_flavour(camera_model)} OPENCV_FISHEYE")
    if values["k4"]:
        raise DataError(f"{where}: k4 is not part of the OPENCV model (k1 k2 p1 p2 k3); use OPENCV_FISHEYE for k1 .. k4")
    coeffs = [values[k] for k in ("k1", "k2", "p1", "p2", "k3")]
    return _lens("radtan", coeffs, f"{_flavour(camera_model)} {camera_model or 'OPENCV'}")


# sensor_msgs/CameraInfo distortion_model -> (OpenCV model, how many of D it takes, at most)
ROS_LENS_MODELS: dict[str, tuple[str, int]] = {
    "plumb_bob": ("radtan", 5),  # k1 k2 p1 p2 k3
    "rational_polynomial": ("radtan", 8),  # k1 k2 p1 p2 k3 k4 k5 k6
    "equidistant": ("fisheye", 4),  # k1 k2 k3 k4 (ROS' fisheye)
}


def ros_lens(distortion_model: str, d: list[float], where: str) -> Lens | None:
    """The lens of a ``sensor_msgs/CameraInfo`` (``distortion_model``, ``d``); None for a pinhole.

    An empty model with all-zero ``d`` is a pinhole (some drivers write nothing); any other model
    is refused by name rather than treated as one it is not."""
    if not distortion_model and not any(d):
        return None
    if distortion_model not in ROS_LENS_MODELS:
        raise DataError(f"{where}: distortion_model {distortion_model!r} is not supported "
                        f"(expected one of {sorted(ROS_LENS_MODELS)})")
    kind, most = ROS_LENS_MODELS[distortion_model]
    if len(d) > most and any(d[most:]):
        raise DataError(f"{where}: {distortion_model} has at most {most} coefficients, got {len(d)}: {list(d)}")
    coeffs = [float(x) for x in d[:most]] + [0.0] * (most - len(d[:most]))
    return _lens(kind, coeffs, f"ROS {distortion_model}")  # an equidistant lens stays one with k = 0


def _flavour(camera_model: str) -> str:
    return "nerfstudio" if camera_model else "instant-ngp"


def _lens(kind: str, coeffs: list[float], name: str) -> Lens | None:
    if not all(math.isfinite(c) for c in coeffs):
        raise DataError(f"{name}: distortion coefficients must be finite, got {coeffs}")
    if kind == "radtan" and not any(coeffs):
        return None  # a pinhole written in a distortion model's terms
    if kind == "radtan" and len(coeffs) == 5 and coeffs[4] == 0.0:
        coeffs = coeffs[:4]
    return Lens(kind, tuple(float(c) for c in coeffs), name)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Undistortion:
    """A distorted camera of one image size and the pinhole camera of that size that replaces it.

    ``map_x``/``map_y`` give, for every output pixel, its source position in the distorted image
    (OpenCV coordinates: pixel i centred at i), all inside the image.
    """

    lens: Lens
    size: tuple[int, int]  # (W, H), before and after
    source_intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy of the distorted camera
    intrinsics: tuple[float, float, float, float]  # of the pinhole camera replacing it
    method: str  # how the pinhole camera was chosen, for meta["notes"]
    map_x: np.ndarray = field(repr=False)  # [H, W] float32
    map_y: np.ndarray = field(repr=False)  # [H, W] float32

    def image(self, img: np.ndarray) -> np.ndarray:
        """[H, W, C] float32 -> [H, W, C] (bilinear); RGBA premultiplied, as resizing, so no fringe."""
        if img.shape[2] == 4:
            alpha = img[:, :, 3:4]
            out = self._remap(np.concatenate([img[:, :, :3] * alpha, alpha], axis=2), cv2.INTER_LINEAR)
            a = out[:, :, 3:4]
            rgb = np.where(a > 1e-6, out[:, :, :3] / np.maximum(a, 1e-6), 0.0)
            return np.clip(np.concatenate([rgb, a], axis=2), 0.0, 1.0).astype(np.float32)
        return np.clip(self._remap(img, cv2.INTER_LINEAR), 0.0, 1.0).astype(np.float32)

    def depth(self, depth: np.ndarray, sparse: bool = False) -> np.ndarray:
        """[H, W] z-depth (0 = unknown) -> [H, W]: dense maps by nearest neighbour (depths never
        blended across edges); sparse ones point by point, so that no sample is lost or repeated."""
        if not sparse:
            return self._remap(depth.astype(np.float32), cv2.INTER_NEAREST)
        rows, cols = np.nonzero(depth > 0)
        uv = self.points(np.stack([cols + 0.5, rows + 0.5], axis=1).astype(np.float64))
        out = np.full(depth.shape, np.inf)
        c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (c >= 0) & (c < self.size[0]) & (r >= 0) & (r < self.size[1])
        np.minimum.at(out, (r[ok], c[ok]), depth[rows[ok], cols[ok]])
        out[np.isinf(out)] = 0.0
        return out.astype(np.float32)

    def points(self, uv: np.ndarray) -> np.ndarray:
        """Pixel positions [N, 2] in the distorted image -> their positions in the pinhole image."""
        if len(uv) == 0:
            return np.zeros((0, 2))
        src = pixel_to_opencv(np.asarray(uv, dtype=np.float64)).reshape(-1, 1, 2)
        k, new_k = opencv_camera_matrix(self.source_intrinsics), opencv_camera_matrix(self.intrinsics)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
        if self.lens.model == "fisheye":
            out = cv2.fisheye.undistortPoints(src, k, np.array(self.lens.coeffs), R=np.eye(3), P=new_k, criteria=crit)
        else:
            out = cv2.undistortPoints(src, k, np.array(self.lens.coeffs), R=np.eye(3), P=new_k, criteria=crit)
        return opencv_to_pixel(out.reshape(-1, 2))

    def describe(self) -> str:
        w, h = self.size
        fx, fy, cx, cy = self.intrinsics
        fov_in = math.degrees(2 * math.atan(0.5 * w / self.source_intrinsics[0]))
        fov_out = math.degrees(2 * math.atan(0.5 * w / fx))
        return (f"{self.lens.describe()} undone at {w}x{h}, before downscaling: pinhole fx {fx:.2f} fy {fy:.2f} "
                f"cx {cx:.2f} cy {cy:.2f} (nominal horizontal fov {fov_in:.1f} -> {fov_out:.1f} deg; {self.method})")

    def _remap(self, img: np.ndarray, interpolation: int) -> np.ndarray:
        out = cv2.remap(img, self.map_x, self.map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)
        return out if out.ndim == img.ndim else out[:, :, None]


@functools.lru_cache(maxsize=4)  # one map per camera: the images of a capture share it (2 x 4 bytes a pixel)
def undistortion(intrinsics: tuple[float, float, float, float], width: int, height: int, lens: Lens) -> Undistortion:
    """The :class:`Undistortion` of a camera (``intrinsics`` at ``width`` x ``height``, our pixels).

    The pinhole camera is OpenCV's choice of one without invalid pixels
    (``cv2.getOptimalNewCameraMatrix(alpha=0)``, ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify
    (balance=0)``); should any output pixel still map outside the image, the field of view is
    narrowed until none does.
    """
    k = opencv_camera_matrix(intrinsics)
    d = np.array(lens.coeffs, dtype=np.float64)
    size = (int(width), int(height))
    if lens.model == "fisheye":
        new_k = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(k, d, size, np.eye(3), balance=0.0)
        method = "cv2.fisheye.estimateNewCameraMatrixForUndistortRectify, balance 0"
    else:
        new_k, _ = cv2.getOptimalNewCameraMatrix(k, d, size, 0.0)
        method = "cv2.getOptimalNewCameraMatrix, alpha 0"
    for narrowed in range(40):
        map_x, map_y = _maps(lens, k, d, new_k, size)
        outside = (map_x < -0.5) | (map_x > width - 0.5) | (map_y < -0.5) | (map_y > height - 0.5)
        if not outside.any() and np.isfinite(new_k).all():
            break
        new_k = new_k.copy()
        new_k[0, 0] *= 1.02
        new_k[1, 1] *= 1.02
    else:
        raise DataError(f"{lens.describe()}: no pinhole camera of {width}x{height} sees only pixels of the image")
    if narrowed:
        method += f", then the focal length raised {100 * (1.02 ** narrowed - 1):.0f}% so that no pixel lacks a source"
    method += "; every output pixel has a source"
    return Undistortion(lens, size, tuple(float(x) for x in intrinsics), intrinsics_from_opencv_matrix(new_k),  # type: ignore[arg-type]
                        method, map_x, map_y)


def _maps(lens: Lens, k: np.ndarray, d: np.ndarray, new_k: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    init = cv2.fisheye.initUndistortRectifyMap if lens.model == "fisheye" else cv2.initUndistortRectifyMap
    return init(k, d, np.eye(3), new_k, size, cv2.CV_32FC1)
