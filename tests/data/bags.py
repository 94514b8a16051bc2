"""Hand-made ROS 2 bags for the tests, written with ``rosbags``' writer: every message known.

:func:`write_bag` writes a list of (topic, type, time, message) as a rosbag2 (the messages from
:mod:`agent.data.ros.messages`), so that each test can spoil exactly one thing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from agent.data.ros import messages as msg

TS = msg.typestore()
T0 = 1_700_000_000.0
stamp, header, transform, tf_message, image, compressed = (msg.stamp, msg.header, msg.transform, msg.tf_message,
                                                          msg.image, msg.compressed)


def camera_info(t: float, w: int, h: int, k: tuple[float, float, float, float] = (20.0, 20.0, 7.5, 5.5),
                model: str = "plumb_bob", d: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0),
                frame: str = "camera_optical"):
    """A CameraInfo with ``k`` = (fx, fy, cx, cy) as ROS writes them (pixel centres at the index)."""
    fx, fy, cx, cy = k
    return msg.camera_info(t, w, h, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), frame, model, d)


def pose_x(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    """[4, 4]: a translation along x and a turn about z."""
    a = np.radians(yaw_deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[0, 3] = x
    return m


def write_bag(path: Path, messages: list[tuple[str, str, float, object]], storage: str = "mcap",
              empty_topics: tuple[tuple[str, str], ...] = ()) -> Path:
    """(topic, type, receive time s, message) -> a rosbag2 folder at ``path``; ``empty_topics``: declared, unused."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3) as w:
        conns = {}
        for topic, typ in list(dict.fromkeys([(m[0], m[1]) for m in messages])) + list(empty_topics):
            conns[topic] = w.add_connection(topic, typ, typestore=TS)
        for topic, _, t, message in sorted(messages, key=lambda m: m[2]):
            w.write(conns[topic], int(t * 1e9), msg.serialize(message))
    return path


def camera_bag(path: Path, n: int = 6, w: int = 16, h: int = 12, *, storage: str = "mcap", image_dt: float = 0.1,
               tf_dt: float = 0.01, encoding: str = "rgb8", info: dict | None = None, tf: bool = True,
               tf_offset_s: float = 0.0, camera_frame: str = "camera_optical", image_frame: str | None = None,
               moves: float = 0.5, seed: int = 0) -> Path:
    """A robot driving along x (``moves`` units per image) with a camera on a static mount; images of noise.
    ``image_frame``: the images' header.frame_id when it is not the mounted camera's frame."""
    rng = np.random.default_rng(seed)
    mount = np.eye(4)
    mount[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]
    msgs: list = []
    if tf:
        msgs.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 1, tf_message(transform(T0, "base_link", camera_frame, mount))))
        for t in np.arange(T0 - 0.05, T0 + n * image_dt + 0.05, tf_dt) + 0.3 * tf_dt:
            base = pose_x(moves * (t - T0) / image_dt)
            msgs.append(("/tf", "tf2_msgs/msg/TFMessage", t + tf_offset_s,
                         tf_message(transform(t + tf_offset_s, "odom", "base_link", base))))
    for i in range(n):
        t = T0 + i * image_dt
        px = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        msgs.append(("/camera/image_raw", "sensor_msgs/msg/Image", t, image(t, px, encoding, image_frame or camera_frame)))
        msgs.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", t, camera_info(t, w, h, **(info or {}))))
    return write_bag(path, msgs, storage)
