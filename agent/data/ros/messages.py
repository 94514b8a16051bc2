"""ROS 2 messages built in Python (rosbags' Humble types): what a robot's camera, CameraInfo and tf publish.

For writing bags (:mod:`agent.data.ros.record`, the tests, the benchmarks); the reader only
deserialises. Times are seconds (float); transforms are [4, 4] matrices.
"""

from __future__ import annotations

import functools

import numpy as np

from agent.data.ros.tf import matrix_quaternion

__all__ = ["typestore", "serialize", "stamp", "header", "transform", "tf_message", "image", "compressed",
           "camera_info"]


@functools.lru_cache(maxsize=1)
def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _t(name: str):
    return typestore().types[name]


def serialize(msg) -> bytes:
    """CDR bytes of a message, as a bag stores them."""
    return typestore().serialize_cdr(msg, msg.__msgtype__)


def stamp(t: float):
    ns = int(round(t * 1e9))
    return _t("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(t: float, frame: str):
    return _t("std_msgs/msg/Header")(stamp=stamp(t), frame_id=frame)


def transform(t: float, parent: str, child: str, m: np.ndarray):
    """``geometry_msgs/TransformStamped``: ``m`` [4, 4] is T_parent_from_child."""
    q = matrix_quaternion(m)
    return _t("geometry_msgs/msg/TransformStamped")(
        header=header(t, parent), child_frame_id=child,
        transform=_t("geometry_msgs/msg/Transform")(
            translation=_t("geometry_msgs/msg/Vector3")(x=float(m[0, 3]), y=float(m[1, 3]), z=float(m[2, 3])),
            rotation=_t("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))))


def tf_message(*transforms):
    return _t("tf2_msgs/msg/TFMessage")(transforms=list(transforms))


def image(t: float, pixels: np.ndarray, encoding: str, frame: str = "camera_optical", step: int | None = None,
          bigendian: bool = False):
    """``sensor_msgs/Image``: ``pixels`` uint8 [H, W, C] or uint16 [H, W] as ``encoding`` lays them out;
    ``step`` pads the rows (bytes a row)."""
    h, w = pixels.shape[:2]
    if pixels.dtype == np.uint8:
        rows = pixels.reshape(h, -1)
    else:
        rows = np.ascontiguousarray(pixels.astype(">u2" if bigendian else "<u2")).reshape(h, -1).view(np.uint8)
    step = step or rows.shape[1]
    padded = np.zeros((h, step), np.uint8)
    padded[:, :rows.shape[1]] = rows
    return _t("sensor_msgs/msg/Image")(header=header(t, frame), height=h, width=w, encoding=encoding,
                                       is_bigendian=int(bigendian), step=step, data=padded.ravel())


def compressed(t: float, data: bytes, fmt: str, frame: str = "camera_optical"):
    """``sensor_msgs/CompressedImage`` of encoded bytes (``fmt``: jpeg, png, ...)."""
    return _t("sensor_msgs/msg/CompressedImage")(header=header(t, frame), format=fmt,
                                                 data=np.frombuffer(data, np.uint8))


def camera_info(t: float, width: int, height: int, k: np.ndarray, frame: str = "camera_optical", model: str = "plumb_bob",
                d: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)):
    """``sensor_msgs/CameraInfo``: ``k`` the [3, 3] camera matrix in ROS's (OpenCV's) pixel convention."""
    km = np.asarray(k, dtype=np.float64).reshape(3, 3)
    return _t("sensor_msgs/msg/CameraInfo")(
        header=header(t, frame), height=height, width=width, distortion_model=model,
        d=np.asarray(d, dtype=np.float64), k=km.ravel(), r=np.eye(3).ravel(),
        p=np.hstack([km, np.zeros((3, 1))]).ravel(), binning_x=0, binning_y=0,
        roi=_t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
