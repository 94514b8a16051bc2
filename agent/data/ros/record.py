"""Record views as a robot would: a rosbag2 with its camera, CameraInfo, /tf and /tf_static.

For tests, benchmarks and scenarios that need bags from the data at hand (no ROS is installed
here): the images at a fixed rate, the camera on a tilted mount (``base_link -> camera_optical``
in ``/tf_static``), the robot's odometry in ``/tf`` at a multiple of the image rate with the
image stamps falling between transforms (the robot rests at each image's pose for a transform
period either side and moves on a geodesic between, so the views need not be a smooth
trajectory and the pose read back at each image is its true one), a lens distortion synthesised into the pixels and declared in ``CameraInfo``, and the
whole trajectory in the robot's own odometry frame (``T_odom_from_world``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from agent.camera import OPENCV_FROM_OPENGL, opencv_camera_matrix, pixel_to_opencv
from agent.data.ros import messages as msg
from agent.data.ros.tf import matrix_quaternion, quaternion_matrix, slerp
from agent.data.views import Views

__all__ = ["RecordConfig", "record_bag", "mount_transform", "bag_storage_file"]

Encoding = Literal["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "jpeg", "png"]


@dataclass
class RecordConfig:
    storage: Literal["mcap", "sqlite3"] = "mcap"
    image_rate_hz: float = 10.0
    tf_rate_factor: int = 20  # /tf at this multiple of the image rate
    encoding: Encoding = "rgb8"  # jpeg / png: a CompressedImage on <topic>/compressed
    mount_tilt_deg: float = 15.0  # the camera pitched down on the robot
    k1: float = 0.0  # pincushion (>= 0: every distorted pixel has a source) put into the pixels, plumb_bob
    start_s: float = 1_700_000_000.0  # the first image's stamp
    image_topic: str = "/camera/image_raw"
    info_topic: str = "/camera/camera_info"
    fixed_frame: str = "odom"
    base_frame: str = "base_link"
    camera_frame: str = "camera_optical"


def mount_transform(tilt_deg: float) -> np.ndarray:
    """T_base_from_optical [4, 4]: optical z along the robot's x, pitched down ``tilt_deg``, 0.3 up."""
    optical_in_base = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # columns: x, y, z of optical
    a = np.radians(tilt_deg)
    pitch = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    m = np.eye(4)
    m[:3, :3] = pitch @ optical_in_base
    m[:3, 3] = (0.1, 0.0, 0.3)
    return m


def _distortion_maps(intrinsics, width: int, height: int, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted image, where it is in the pinhole image (maps for cv2.remap)."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    uv = pixel_to_opencv(np.stack([u.ravel(), v.ravel()], axis=1)).reshape(-1, 1, 2)
    k = opencv_camera_matrix(intrinsics)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    src = cv2.undistortPoints(uv.astype(np.float64), k, np.array([k1, 0.0, 0.0, 0.0]), P=k, criteria=crit)
    src = src.reshape(height, width, 2).astype(np.float32)  # OpenCV coordinates: what remap takes
    return src[..., 0], src[..., 1]


def _pixels(img: np.ndarray, encoding: str) -> tuple[np.ndarray, str]:
    """float [H, W, 3|4] RGB(A) -> (uint8/uint16 array as the encoding lays it out, encoding)."""
    if encoding in ("mono8", "mono16"):
        grey = img[:, :, :3].mean(axis=2)
        if encoding == "mono16":
            return np.round(grey * 65535).astype("<u2"), encoding
        return np.round(grey * 255).astype(np.uint8), encoding
    q = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    if encoding in ("rgba8", "bgra8") and q.shape[2] == 3:
        q = np.concatenate([q, np.full(q.shape[:2] + (1,), 255, np.uint8)], axis=2)
    if encoding in ("rgb8", "bgr8"):
        q = q[:, :, :3]
    if encoding.startswith("bgr"):
        q = q[:, :, [2, 1, 0, 3][: q.shape[2]]]
    return np.ascontiguousarray(q), encoding


def _base_poses(views: Views, t_odom_from_world: np.ndarray, mount: np.ndarray) -> np.ndarray:
    """[M, 4, 4] base_link in odom at each image: the camera's true pose carried back through the mount."""
    optical = views.c2w.double().numpy() @ OPENCV_FROM_OPENGL  # [M, 4, 4] world <- optical
    return t_odom_from_world @ optical @ np.linalg.inv(mount)


def _interpolate(poses: np.ndarray, stamps: np.ndarray, t: float, hold: float) -> np.ndarray:
    """The robot at ``t``: at ``poses[i]`` within ``hold`` of ``stamps[i]`` (so that the transforms
    around an image stamp are its true pose, whatever the views' order), on the geodesic between."""
    i = int(np.searchsorted(stamps, t)) - 1
    if i < 0 or t <= stamps[i] + hold:
        return poses[max(i, 0)]
    if i + 1 >= len(stamps) or t >= stamps[i + 1] - hold:
        return poses[min(i + 1, len(poses) - 1)]
    s = (t - stamps[i] - hold) / (stamps[i + 1] - stamps[i] - 2 * hold)
    q = slerp(matrix_quaternion(poses[i]), matrix_quaternion(poses[i + 1]), s)
    return quaternion_matrix((1 - s) * poses[i][:3, 3] + s * poses[i + 1][:3, 3], q)


def bag_storage_file(bag_dir: str | Path) -> Path:
    """The one storage file (``.mcap`` / ``.db3``) of a bag folder :func:`record_bag` wrote."""
    files = sorted(p for p in Path(bag_dir).iterdir() if p.suffix in (".mcap", ".db3"))
    if len(files) != 1:
        raise FileNotFoundError(f"{bag_dir}: expected one .mcap or .db3 file, found {[p.name for p in files]}")
    return files[0]


def record_bag(views: Views, path: str | Path, t_odom_from_world: np.ndarray, cfg: RecordConfig | None = None) -> dict:
    """Write ``views`` (pinhole, in capture order) as a rosbag2 folder at ``path``; returns what was written."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    cfg = cfg or RecordConfig()
    ts = msg.typestore()
    mount = mount_transform(cfg.mount_tilt_deg)
    base = _base_poses(views, np.asarray(t_odom_from_world, dtype=np.float64), mount)
    dt = 1.0 / cfg.image_rate_hz
    stamps = cfg.start_s + dt * np.arange(len(views))
    tf_dt = dt / cfg.tf_rate_factor
    tf_times = np.arange(stamps[0] - 2 * tf_dt, stamps[-1] + 2 * tf_dt, tf_dt) + 0.37 * tf_dt  # images fall between
    k = views.intrinsics[0].tolist()
    maps = _distortion_maps(k, views.width, views.height, cfg.k1) if cfg.k1 else None
    compressed = cfg.encoding in ("jpeg", "png")
    plugin = StoragePlugin.MCAP if cfg.storage == "mcap" else StoragePlugin.SQLITE3
    written = {"images": 0, "tf": 0}
    with Writer(Path(path), version=9, storage_plugin=plugin) as w:
        image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        c_img = w.add_connection(cfg.image_topic + ("/compressed" if compressed else ""), image_type, typestore=ts)
        c_info = w.add_connection(cfg.info_topic, "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        static = msg.tf_message(msg.transform(stamps[0], cfg.base_frame, cfg.camera_frame, mount))
        w.write(c_static, int(tf_times[0] * 1e9), msg.serialize(static))
        events = [(t, "tf", None) for t in tf_times] + [(t, "image", i) for i, t in enumerate(stamps)]
        for t, kind, i in sorted(events, key=lambda e: e[0]):
            if kind == "tf":
                odom = msg.transform(t, cfg.fixed_frame, cfg.base_frame, _interpolate(base, stamps, t, tf_dt))
                w.write(c_tf, int(t * 1e9), msg.serialize(msg.tf_message(odom)))
                written["tf"] += 1
                continue
            img = views.images[i].numpy()
            if maps is not None:
                img = np.clip(cv2.remap(img, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), 0, 1)
            w.write(c_img, int(t * 1e9), msg.serialize(_image_message(img, t, cfg)))
            info = msg.camera_info(t, views.width, views.height, opencv_camera_matrix(k), cfg.camera_frame,
                                   d=(cfg.k1, 0.0, 0.0, 0.0, 0.0))
            w.write(c_info, int(t * 1e9), msg.serialize(info))
            written["images"] += 1
    return {**written, "stamps_s": stamps.tolist(), "T_odom_from_world": np.asarray(t_odom_from_world).tolist(),
            "T_base_from_optical": mount.tolist()}


def _image_message(img: np.ndarray, t: float, cfg: RecordConfig):
    """An image [H, W, 3|4] float as the configured encoding: raw, or jpeg/png compressed (png keeps alpha)."""
    if cfg.encoding in ("jpeg", "png"):
        q, _ = _pixels(img, "rgba8" if img.shape[2] == 4 and cfg.encoding == "png" else "rgb8")
        q = q[:, :, [2, 1, 0, 3][: q.shape[2]]]  # OpenCV writes BGR(A)
        _, buf = cv2.imencode(".jpg" if cfg.encoding == "jpeg" else ".png", q)
        return msg.compressed(t, buf.tobytes(), cfg.encoding, cfg.camera_frame)
    q, enc = _pixels(img, cfg.encoding)
    return msg.image(t, q, enc, cfg.camera_frame)
