"""ROS 2 messages as they arrive -> posed, undistorted keyframes, one at a time.

What :mod:`agent.data.ros.bag` does to a whole bag, done incrementally for a robot that maps
while it moves: messages come from a bag replayed at its recorded pace (:func:`replay_bag`) or
from the live camera over Zenoh (``protocol.ros_camera`` hands them to :meth:`FrameIntake.feed`;
this module never sees Zenoh). The same parts: the tf tree (:mod:`agent.data.ros.tf`, a pose
at the image's own stamp, interpolated, never extrapolated), the camera
(:mod:`agent.data.ros.decode`) and the keyframe rule (:class:`OnlineKeyframer`).

An image whose stamp is past the newest ``/tf`` waits for tf to catch up, at most
``tf_wait_s``; then, as every image without a pose, it is counted by reason and skipped.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agent.camera import opencv_to_opengl_c2w
from agent.data.lens import undistortion
from agent.data.ros.bag import CAMERA_INFO, COMPRESSED, IMAGE, TF, _Bag, _choose_image_topic, _stamp
from agent.data.ros.config import RosBagConfig
from agent.data.ros.decode import CameraModel, camera_model, decode_compressed, decode_image, grey_sharpness
from agent.data.ros.keyframes import OnlineKeyframer
from agent.data.ros.tf import NoTransform, TfTree
from agent.data.views import DataError
from protocol.pacing import paced

__all__ = ["Keyframe", "FrameIntake", "replay_bag"]


@dataclass
class Keyframe:
    """One admitted camera frame: undistorted pixels at the camera's size and its pose."""

    name: str
    image: np.ndarray  # [H, W, 3|4] float32 in [0, 1]
    c2w: np.ndarray  # [4, 4] OpenGL camera-to-world in the fixed frame
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy (pinhole, pixel centres at +0.5)
    stamp_ns: int  # header stamp
    received_ns: int  # when it reached this robot (wall clock)
    ready_ns: int = 0  # when it was posed and chosen (wall clock)


@dataclass
class _Pending:
    index: int
    stamp_ns: int
    frame_id: str
    msg: object
    topic: str
    ros_type: str
    received_ns: int
    pixels: np.ndarray | None = None  # decoded once, when the keyframe rule needs them


class FrameIntake:
    """Feeds on tf, CameraInfo and image messages; :meth:`take` returns the keyframes completed so far.

    Thread-safe: a replay thread or Zenoh's callbacks feed it while the daemon trains."""

    def __init__(self, cfg: RosBagConfig, image_topic: str, info_topic: str | None = None,
                 tf_wait_s: float = 1.0) -> None:
        self.cfg, self.image_topic, self.tf_wait_ns = cfg, image_topic, int(tf_wait_s * 1e9)
        self.info_topic = info_topic
        self.tf = TfTree(cfg.tf_max_gap_s)
        self.camera: CameraModel | None = None
        self.keyframer = OnlineKeyframer(cfg.keyframes)
        self.skipped: Counter[str] = Counter()  # images without a pose, by reason
        self.images = 0
        self.notes: list[str] = []
        self._pending: list[_Pending] = []
        self._done: list[Keyframe] = []
        self._lock = threading.Lock()
        self._tf_sorted = True
        self._newest_tf = -1
        self._und = None
        self.fixed_frame = cfg.fixed_frame

    # ------------------------------------------------------------------ feeding
    def feed(self, topic: str, ros_type: str, msg, received_ns: int | None = None) -> None:
        """One deserialised message (rosbags' types, as the bag reader and ``protocol.ros_camera`` give)."""
        received_ns = time.time_ns() if received_ns is None else received_ns
        with self._lock:
            if ros_type == TF:
                self._add_tf(topic, msg)
            elif ros_type == CAMERA_INFO and (self.info_topic is None or topic == self.info_topic):
                if self.camera is None:
                    self.camera = camera_model(msg, topic)
            elif ros_type in (IMAGE, COMPRESSED) and topic == self.image_topic:
                frame = self.cfg.camera_frame or str(msg.header.frame_id)
                self._pending.append(_Pending(self.images, _stamp(msg.header), frame, msg, topic, ros_type, received_ns))
                self.images += 1
            self._pose_pending(received_ns)

    def _add_tf(self, topic: str, msg) -> None:
        static = topic.endswith("tf_static")
        for ts in msg.transforms:
            tr, rot = ts.transform.translation, ts.transform.rotation
            stamp = _stamp(ts.header)
            try:
                self.tf.add(ts.header.frame_id, ts.child_frame_id, stamp, (tr.x, tr.y, tr.z),
                            (rot.x, rot.y, rot.z, rot.w), static)
            except ValueError as e:
                self.skipped["bad_tf"] += 1
                if len(self.notes) < 5:
                    self.notes.append(f"{topic}: {e}")
                continue
            if not static:
                self._tf_sorted = self._tf_sorted and stamp >= self._newest_tf
                self._newest_tf = max(self._newest_tf, stamp)

    def _pose_pending(self, now_ns: int) -> None:
        """Pose the waiting images that tf now covers (or never will); offer them to the keyframer."""
        if not self._pending:
            return
        if self.camera is None:  # no CameraInfo yet: images wait for it as for tf, then are skipped
            keep = [p for p in self._pending if now_ns - p.received_ns < self.tf_wait_ns]
            if len(keep) < len(self._pending):
                self.skipped["no_camera_info"] += len(self._pending) - len(keep)
            self._pending = keep
            return
        if not self._tf_sorted:
            self.tf.finish()
            self._tf_sorted = True
        keep = []
        for p in self._pending:
            c2w, reason = self._pose(p)
            if c2w is None and reason == "wait" and now_ns - p.received_ns < self.tf_wait_ns:
                keep.append(p)
                continue
            if c2w is None:
                self.skipped["outside_tf" if reason == "wait" else reason] += 1
                continue
            kept = self.keyframer.offer(c2w, (p, c2w), self._sharpness)
            if kept is not None:
                self._done.append(self._keyframe(*kept))
        self._pending = keep

    def _pose(self, p: _Pending) -> tuple[np.ndarray | None, str]:
        frame = p.frame_id.lstrip("/")
        if frame not in self.tf.frames:
            return None, "wait"  # its /tf_static may still come
        if self.tf.dynamic_span is None or p.stamp_ns > self._newest_tf:
            return None, "wait"  # a moving camera's pose needs /tf up to its stamp
        fixed = self.fixed_frame or self.tf.root(frame)
        try:
            c2w = opencv_to_opengl_c2w(self.tf.lookup(fixed, frame, p.stamp_ns))
        except NoTransform as e:
            return None, e.reason
        self.fixed_frame = fixed  # the first pose fixes the frame: a later link above the root must not move it
        return c2w, ""

    def _decoded(self, p: _Pending) -> np.ndarray:
        if p.pixels is None:
            img = decode_image(p.msg, p.topic) if p.ros_type == IMAGE else decode_compressed(p.msg, p.topic)
            h, w = img.shape[:2]
            if (self.camera.width, self.camera.height) not in ((w, h), (0, 0)):
                raise DataError(f"{self.info_topic or 'CameraInfo'} is for {self.camera.width}x{self.camera.height} "
                                f"images but {p.topic} has {w}x{h}")
            p.pixels = img
            p.msg = None  # the pixels are all that is needed now
        return p.pixels

    def _sharpness(self, item) -> float:
        return grey_sharpness(self._decoded(item[0]))

    def _keyframe(self, p: _Pending, c2w: np.ndarray) -> Keyframe:
        img, intrinsics = self._decoded(p), self.camera.intrinsics
        if self.camera.lens is not None:
            self._und = self._und or undistortion(intrinsics, img.shape[1], img.shape[0], self.camera.lens)
            img, intrinsics = self._und.image(img), self._und.intrinsics
        return Keyframe(f"frame_{p.index:06d}", img, c2w, tuple(float(x) for x in intrinsics), p.stamp_ns,
                        p.received_ns, time.time_ns())

    # ------------------------------------------------------------------ taking
    def take(self) -> list[Keyframe]:
        """The keyframes completed since the last call, in order; images still waiting for tf are posed first."""
        with self._lock:
            self._pose_pending(time.time_ns())
            out, self._done = self._done, []
        return out

    def finish(self) -> list[Keyframe]:
        """The source ended: the last window closes, images still waiting are skipped."""
        with self._lock:
            self._pose_pending(time.time_ns() + self.tf_wait_ns)
            last = self.keyframer.flush()
            if last is not None:
                self._done.append(self._keyframe(*last))
            out, self._done = self._done, []
        return out

    @property
    def dropped(self) -> int:
        """Frames that will never be keyframes for a reason other than the rule: no pose, over budget."""
        return sum(self.skipped.values()) + self.keyframer.dropped


def replay_bag(path: str | Path, intake: FrameIntake, rate: float, stop: threading.Event) -> int:
    """Feed a bag's camera, CameraInfo and tf to ``intake`` at ``rate`` x its recorded pace (receive
    times); returns the messages fed. The bag's damage is one :class:`DataError`, as for the loader."""
    bag = _Bag(Path(path))
    try:
        conns = [c for c in bag.connections if c.msgtype == TF or c.topic in (intake.image_topic, intake.info_topic)
                 or (intake.info_topic is None and c.msgtype == CAMERA_INFO)]
        fed = 0
        for conn, msg in paced(((t, (conn, msg)) for conn, t, msg in bag.messages(conns)), rate, stop):
            intake.feed(conn.topic, conn.msgtype, msg)
            fed += 1
        return fed
    finally:
        bag.close()


def bag_image_topic(path: str | Path, cfg: RosBagConfig) -> tuple[str, str | None]:
    """The camera topic of a bag (its one camera, or ``cfg.image_topic``) and its CameraInfo topic."""
    from agent.data.ros.bag import _choose_info_topic

    bag = _Bag(Path(path))
    try:
        topic, _ = _choose_image_topic(bag, cfg)
        return topic, _choose_info_topic(bag, cfg, topic)
    finally:
        bag.close()
