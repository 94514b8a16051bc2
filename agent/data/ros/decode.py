"""ROS 2 camera messages -> pixels and a camera: ``sensor_msgs/Image``, ``CompressedImage``, ``CameraInfo``.

Images come out as the rest of the project wants them (:mod:`agent.data.views`): float32
``[H, W, 3|4]`` straight colour in [0, 1], RGB(A) order. ``rgba8``/``bgra8`` keep their alpha
(a mask recorded with the image); ``mono8``/``mono16`` become grey RGB. Any other encoding is
refused in one line that names the topic and the encoding, never guessed.
"""

from __future__ import annotations

import cv2
import numpy as np

from agent.camera import intrinsics_from_opencv_matrix
from agent.data.lens import Lens, ros_lens
from agent.data.views import DataError

__all__ = ["ENCODINGS", "decode_image", "decode_compressed", "CameraModel", "camera_model", "grey_sharpness"]

# encoding -> (channels, bytes per channel, channel order to RGB(A))
ENCODINGS: dict[str, tuple[int, int, list[int] | None]] = {
    "rgb8": (3, 1, None), "bgr8": (3, 1, [2, 1, 0]), "rgba8": (4, 1, None), "bgra8": (4, 1, [2, 1, 0, 3]),
    "mono8": (1, 1, None), "mono16": (1, 2, None),
}


def decode_image(msg, topic: str) -> np.ndarray:
    """``sensor_msgs/msg/Image`` -> [H, W, 3|4] float32 in [0, 1]."""
    enc = str(msg.encoding).lower()
    if enc not in ENCODINGS:
        raise DataError(f"{topic}: image encoding {msg.encoding!r} is not supported (expected one of {sorted(ENCODINGS)})")
    channels, size, order = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if h < 1 or w < 1 or step < w * channels * size or len(data) < step * h:
        raise DataError(f"{topic}: image of {w}x{h} {enc} with step {step} holds {len(data)} bytes, "
                        f"expected at least {w * channels * size * h}")
    rows = data[: step * h].reshape(h, step)[:, : w * channels * size]
    if size == 2:
        dtype = ">u2" if msg.is_bigendian else "<u2"
        img = rows.copy().view(dtype).reshape(h, w, channels).astype(np.float32) / 65535.0
    else:
        img = rows.reshape(h, w, channels).astype(np.float32) / 255.0
    if channels == 1:
        img = np.repeat(img, 3, axis=2)
    elif order is not None:
        img = img[:, :, order]
    return np.ascontiguousarray(img)


def decode_compressed(msg, topic: str) -> np.ndarray:
    """``sensor_msgs/msg/CompressedImage`` (jpeg or png; a png keeps its alpha) -> [H, W, 3|4] float32."""
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt or not any(k in fmt for k in ("jpeg", "jpg", "png")):
        raise DataError(f"{topic}: compressed image format {msg.format!r} is not supported (expected jpeg or png)")
    buf = np.asarray(msg.data, dtype=np.uint8)
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        raw = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if len(buf) else None
    finally:
        log.setLogLevel(level)
    if raw is None:
        raise DataError(f"{topic}: a {msg.format!r} image of {len(buf)} bytes cannot be decoded")
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    img = raw.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    return np.ascontiguousarray(img)


class CameraModel:
    """A CameraInfo as a camera: intrinsics at the image size, and its lens (None: a pinhole)."""

    def __init__(self, width: int, height: int, intrinsics: tuple[float, float, float, float], lens: Lens | None) -> None:
        self.width, self.height, self.intrinsics, self.lens = width, height, intrinsics, lens

    def describe(self) -> str:
        fx, fy, cx, cy = self.intrinsics
        lens = self.lens.describe() if self.lens is not None else "pinhole (no distortion)"
        return f"{self.width}x{self.height}, fx {fx:.2f} fy {fy:.2f} cx {cx:.2f} cy {cy:.2f}; lens {lens}"


def camera_model(msg, topic: str) -> CameraModel:
    """``sensor_msgs/msg/CameraInfo`` -> :class:`CameraModel`, refusing what cannot be a camera.

    ROS (OpenCV) pixel coordinates put a pixel's centre at its index, ours at index + 0.5
    (agent.camera), so the principal point moves by half a pixel."""
    k = [float(x) for x in msg.k]
    fx, fy = k[0], k[4]
    where = f"{topic}"
    if not all(np.isfinite(k)) or fx <= 0 or fy <= 0:
        raise DataError(f"{where}: CameraInfo has no usable intrinsics (k = {k}): fx and fy must be > 0 "
                        "(an uncalibrated camera publishes zeros; calibrate it, e.g. camera_calibration)")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1 or int(msg.roi.width) or int(msg.roi.height):
        raise DataError(f"{where}: CameraInfo with binning or a region of interest is not supported")
    lens = ros_lens(str(msg.distortion_model), [float(x) for x in msg.d], f"{where}: CameraInfo")
    return CameraModel(int(msg.width), int(msg.height), intrinsics_from_opencv_matrix(np.array(k).reshape(3, 3)), lens)


def grey_sharpness(img: np.ndarray, width: int = 160) -> float:
    """Variance of the Laplacian of the image's grey level at ``width`` px (motion blur lowers it)."""
    h, w = img.shape[:2]
    if w > width:
        img = cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    grey = img[:, :, :3].mean(axis=2).astype(np.float32)
    return float(cv2.Laplacian(grey, cv2.CV_32F).var())
