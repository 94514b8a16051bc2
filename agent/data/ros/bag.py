"""A robot's ROS 2 bag (rosbag2: MCAP or sqlite3) -> its keyframes, as a folder every loader reads.

Read with ``rosbags`` (pure Python; no ROS installation). Two passes over the bag:

1. ``/tf_static``, ``/tf``, ``CameraInfo`` and the image headers: the tf tree, the camera, and
   each image's stamp and frame. Every image gets its camera's pose in the fixed frame at its
   own header stamp (:mod:`agent.data.ros.tf`), or a reason why it has none; the keyframes are
   planned on those poses (:mod:`agent.data.ros.keyframes`).
2. The images again: only those in a keyframe's window are decoded, and the sharpest of each is
   undistorted at its native size and written as a PNG.

The result is a nerfstudio folder (``transforms.json`` PINHOLE, OpenGL camera-to-world in the
fixed frame, ``images/``) with ``bag.json`` beside it (the source, the settings and what was
kept and skipped, and why). A robot's run folder keeps it (``keyframes/``), so that training,
evaluation and export see the same keyframes, and no image is held in memory beyond a window.

Conventions (docs/design.md, "ROS 2 bags"): the camera's ``header.frame_id`` is a ROS optical
frame (x right, y down, z forward), turned into the project's OpenGL camera (x right, y up, z
backward) by flipping y and z (:func:`agent.camera.opencv_to_opengl_c2w`).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import sqlite3
import struct
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from agent.camera import opencv_to_opengl_c2w
from agent.data.folder import matrix_to_list, write_json, write_png
from agent.data.lens import undistortion
from agent.data.ros.config import RosBagConfig
from agent.data.ros.decode import ENCODINGS, CameraModel, camera_model, decode_compressed, decode_image, grey_sharpness
from agent.data.ros.keyframes import plan_keyframes
from agent.data.ros.tf import NoTransform, TfTree
from agent.data.views import DataError, Views
from agent.progress import track

__all__ = ["is_bag", "BagReport", "extract_keyframes", "load_bag", "IMAGE_TYPES", "BAG_RECORD"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF = "tf2_msgs/msg/TFMessage"
BAG_RECORD = "bag.json"
BAG_SUFFIXES = (".mcap", ".db3")


def is_bag(path: Path) -> bool:
    """A rosbag2 file (``.mcap``, ``.db3``) or folder (``metadata.yaml`` beside its storage files)."""
    if path.is_file():
        return path.suffix.lower() in BAG_SUFFIXES
    return path.is_dir() and (path / "metadata.yaml").is_file()


@dataclass
class BagReport:
    """What a bag held and what became of it: ``inspect`` prints it, ``bag.json`` keeps it."""

    path: str
    storage: str = ""
    duration_s: float = 0.0
    topics: list[tuple[str, str, int]] = field(default_factory=list)  # (name, type, messages)
    image_topic: str = ""
    image_type: str = ""
    camera_info_topic: str = ""
    camera: str = ""  # CameraModel.describe()
    lens: str = ""  # the lens model undone at load ("" for a pinhole camera)
    fixed_frame: str = ""
    camera_frame: str = ""
    tf_chain: str = ""
    images: int = 0
    posed: int = 0
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> images without a pose
    keyframes: int = 0
    min_translation: float = 0.0  # the keyframe thresholds used (raised to fit the budget)
    min_rotation_deg: float = 0.0
    candidates_unbudgeted: int = 0
    decoded: int = 0
    messages_read: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def lines(self) -> list[tuple[str, str]]:
        """(what, value) rows for a table."""
        skipped = ", ".join(f"{n} {r}" for r, n in sorted(self.skipped.items())) or "none"
        return [
            ("bag", f"{self.path} ({self.storage}, {self.duration_s:.1f} s)"),
            ("topics", "; ".join(f"{n} ({t.rsplit('/', 1)[-1]}, {c})" for n, t, c in self.topics)),
            ("camera stream", f"{self.image_topic} ({self.image_type.rsplit('/', 1)[-1]}), info {self.camera_info_topic}"),
            ("camera", self.camera),
            ("tf chain", f"{self.tf_chain} (fixed frame {self.fixed_frame})"),
            ("images", f"{self.images}: {self.posed} with a pose, skipped without one: {skipped}"),
            ("keyframes", f"{self.keyframes} kept (moved >= {self.min_translation:.4g} or turned >= "
                          f"{self.min_rotation_deg:.3g} deg, the sharpest of each window; the settings alone gave "
                          f"{self.candidates_unbudgeted}); {self.posed - self.keyframes} posed frames not kept"),
            ("read", f"{self.messages_read} messages in {self.seconds:.1f} s "
                     f"({1000 * self.seconds / max(self.messages_read, 1):.2f} s per thousand), {self.decoded} images decoded"),
        ]


_READ_ERRORS = (sqlite3.DatabaseError, struct.error, EOFError, OSError, KeyError, IndexError, ValueError, AssertionError)


class _Bag:
    """An open bag: its connections by role, and messages read with one-line errors."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self._errors = (AnyReaderError, *_READ_ERRORS)
        if not path.exists():
            raise DataError(f"{path}: no such bag (expected a rosbag2 folder, a .mcap or a .db3 file)")
        try:
            self.reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self.reader.open()
        except self._errors as e:
            raise DataError(f"{path}: not a readable rosbag2 recording: truncated, damaged or not a bag "
                            f"({_short(e)})") from None
        self.connections = list(self.reader.connections)

    def close(self) -> None:
        try:
            self.reader.close()
        except self._errors:
            pass

    def topics(self) -> list[tuple[str, str, int]]:
        counts: dict[tuple[str, str], int] = {}
        for c in self.connections:
            counts[(c.topic, c.msgtype)] = counts.get((c.topic, c.msgtype), 0) + int(c.msgcount)
        return [(t, ty, n) for (t, ty), n in sorted(counts.items())]

    def of_type(self, *types: str) -> list:
        return [c for c in self.connections if c.msgtype in types]

    def messages(self, connections: list) -> Iterator[tuple[object, int, object]]:
        """(connection, receive time ns, message), deserialised; a damaged bag is one DataError."""
        try:
            for conn, t, raw in self.reader.messages(connections=connections):
                yield conn, t, self.reader.deserialize(raw, conn.msgtype)
        except self._errors as e:
            raise DataError(f"{self.path}: the bag is damaged or truncated ({_short(e)})") from None


def _short(e: BaseException) -> str:
    text = str(e).splitlines()[0] if str(e) else ""
    return f"{type(e).__name__}: {text[:160]}" if text else type(e).__name__


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _choose_image_topic(bag: _Bag, cfg: RosBagConfig) -> tuple[str, str]:
    """(topic, type) of the camera: the configured one, or the bag's only one."""
    streams: dict[str, str] = {c.topic: c.msgtype for c in bag.of_type(*IMAGE_TYPES)}
    listed = ", ".join(f"{t} ({ty.rsplit('/', 1)[-1]})" for t, ty in sorted(streams.items()))
    if cfg.image_topic is not None:
        if cfg.image_topic not in streams:
            raise DataError(f"{bag.path}: data.ros.image_topic {cfg.image_topic!r} is not a camera topic of the bag "
                            f"(camera topics: {listed or 'none'})")
        return cfg.image_topic, streams[cfg.image_topic]
    if not streams:
        topics = ", ".join(t for t, _, _ in bag.topics()) or "none"
        raise DataError(f"{bag.path}: no usable camera: no {IMAGE} or {COMPRESSED} topic (topics: {topics})")
    raw = {t for t in streams if f"{t}/compressed" not in streams}  # image_transport's copy of one camera
    cameras = sorted(t for t in streams if t in raw or not t.endswith("/compressed"))
    if len(cameras) > 1:
        raise DataError(f"{bag.path}: {len(cameras)} cameras ({listed}): choose one with "
                        f"--set data.ros.image_topic=\"{cameras[0]}\"")
    topic = cameras[0]
    return topic, streams[topic]


def _choose_info_topic(bag: _Bag, cfg: RosBagConfig, image_topic: str) -> str:
    infos = sorted({c.topic for c in bag.of_type(CAMERA_INFO)})
    if cfg.camera_info_topic is not None:
        if cfg.camera_info_topic not in infos:
            raise DataError(f"{bag.path}: data.ros.camera_info_topic {cfg.camera_info_topic!r} is not a CameraInfo "
                            f"topic of the bag ({', '.join(infos) or 'none'})")
        return cfg.camera_info_topic
    if not infos:
        raise DataError(f"{bag.path}: no {CAMERA_INFO} topic: the camera's intrinsics are unknown (record the "
                        "camera's camera_info with its images)")

    def shared(t: str) -> int:  # path components shared with the image topic
        a, b = t.strip("/").split("/"), image_topic.strip("/").split("/")
        n = 0
        while n < min(len(a), len(b)) and a[n] == b[n]:
            n += 1
        return n

    return max(infos, key=lambda t: (shared(t), t == infos[0]))


@dataclass
class _Frame:
    index: int  # position in the image topic
    stamp: int  # header stamp, ns
    frame_id: str


def _first_pass(bag: _Bag, cfg: RosBagConfig, report: BagReport) -> tuple[TfTree, CameraModel, list[_Frame]]:
    """The tf tree, the camera and every image's stamp and frame (no pixel decoded)."""
    tf = TfTree(cfg.tf_max_gap_s)
    tf_conns = bag.of_type(TF)
    image_conns = [c for c in bag.connections if c.topic == report.image_topic]
    info_conns = [c for c in bag.connections if c.topic == report.camera_info_topic]
    camera: CameraModel | None = None
    frames: list[_Frame] = []
    total = sum(int(c.msgcount) for c in tf_conns + image_conns + info_conns)
    for conn, _, msg in track(bag.messages(tf_conns + image_conns + info_conns), f"reading {bag.path.name}", total):
        report.messages_read += 1
        if conn.msgtype == TF:
            static = conn.topic.endswith("tf_static")
            for ts in msg.transforms:
                tr, rot = ts.transform.translation, ts.transform.rotation
                try:
                    tf.add(ts.header.frame_id, ts.child_frame_id, _stamp(ts.header), (tr.x, tr.y, tr.z),
                           (rot.x, rot.y, rot.z, rot.w), static)
                except ValueError as e:
                    raise DataError(f"{bag.path}: {conn.topic}: {e}") from None
        elif conn.msgtype == CAMERA_INFO:
            if camera is None:
                camera = camera_model(msg, conn.topic)
        else:
            if not frames and conn.msgtype == IMAGE and str(msg.encoding).lower() not in ENCODINGS:
                decode_image(msg, conn.topic)  # refuses the encoding in one line, before any work
            frames.append(_Frame(len(frames), _stamp(msg.header), cfg.camera_frame or str(msg.header.frame_id)))
    if not frames:
        raise DataError(f"{bag.path}: the camera topic {report.image_topic} has no messages")
    if camera is None:
        raise DataError(f"{bag.path}: {report.camera_info_topic} has no messages: the camera's intrinsics are unknown")
    if not tf.links:
        raise DataError(f"{bag.path}: no /tf or /tf_static in the bag: the camera has no pose")
    return tf.finish(), camera, frames


def _check_clock(bag: _Bag, tf: TfTree, frames: list[_Frame]) -> None:
    """Image stamps and /tf from different clocks (sim time against wall time) give no pose at all: say so."""
    if tf.dynamic_span is None:
        return
    lo, hi = tf.dynamic_span
    stamps = np.array([f.stamp for f in frames], dtype=np.int64)
    inside = (stamps >= lo) & (stamps <= hi)
    if not inside.any():
        gap = min(abs(int(stamps.min()) - hi), abs(lo - int(stamps.max()))) * 1e-9
        raise DataError(f"{bag.path}: clock mismatch: image stamps span {stamps.min() * 1e-9:.3f}-{stamps.max() * 1e-9:.3f} s "
                        f"but /tf spans {lo * 1e-9:.3f}-{hi * 1e-9:.3f} s ({gap:.1f} s apart): were they stamped by "
                        "different clocks (use_sim_time)?")


def _poses(bag: _Bag, cfg: RosBagConfig, tf: TfTree, frames: list[_Frame], report: BagReport
           ) -> tuple[list[_Frame], np.ndarray]:
    """The frames with a pose and their OpenGL c2w [N, 4, 4] in the fixed frame; reasons for the rest."""
    camera_frame = frames[0].frame_id
    if not camera_frame:
        raise DataError(f"{bag.path}: the images have no header.frame_id: set data.ros.camera_frame")
    if camera_frame.lstrip("/") not in tf.frames:
        raise DataError(f"{bag.path}: missing tf link: the camera frame {camera_frame!r} is not in the tf tree "
                        f"(frames: {', '.join(sorted(tf.frames))})")
    fixed = cfg.fixed_frame or tf.root(camera_frame)
    if fixed.lstrip("/") not in tf.frames or tf.root(fixed) != tf.root(camera_frame):
        raise DataError(f"{bag.path}: missing tf link: no chain from the camera frame {camera_frame!r} to the fixed "
                        f"frame {fixed!r} (the camera's chain: {tf.describe(camera_frame)})")
    report.fixed_frame, report.camera_frame, report.tf_chain = fixed, camera_frame, tf.describe(camera_frame)
    _check_clock(bag, tf, frames)
    posed, c2w = [], []
    for f in frames:
        try:
            m = tf.lookup(fixed, f.frame_id, f.stamp)
        except NoTransform as e:
            report.skipped[e.reason] = report.skipped.get(e.reason, 0) + 1
            if len(report.notes) < 3:
                report.notes.append(f"image {f.index}: no pose: {e}")
            continue
        posed.append(f)
        c2w.append(opencv_to_opengl_c2w(m))
    report.posed = len(posed)
    if not posed:
        reasons = ", ".join(f"{n} {r}" for r, n in sorted(report.skipped.items()))
        raise DataError(f"{bag.path}: none of the {len(frames)} images has a pose in {fixed!r} ({reasons}; "
                        f"{report.notes[0] if report.notes else ''})")
    return posed, np.stack(c2w)


def _decode(conn, msg) -> np.ndarray:
    return decode_image(msg, conn.topic) if conn.msgtype == IMAGE else decode_compressed(msg, conn.topic)


def _write_keyframes(bag: _Bag, cfg: RosBagConfig, camera: CameraModel, posed: list[_Frame], c2w: np.ndarray,
                     out: Path, report: BagReport) -> None:
    """Second pass: decode each window, keep its sharpest frame, undistort it and write it."""
    plan = plan_keyframes(c2w, cfg.keyframes)
    report.min_translation, report.min_rotation_deg = plan.min_translation, plan.min_rotation_deg
    report.candidates_unbudgeted = plan.triggers_unbudgeted
    window_of = {posed[i].index: w for w, idxs in enumerate(plan.windows) for i in idxs}
    pose_of = {f.index: k for k, f in enumerate(posed)}
    best: dict[int, tuple[float, int, np.ndarray]] = {}  # window -> (sharpness, frame index, image)
    written: list[dict] = []
    (out / "images").mkdir(parents=True, exist_ok=True)
    und, size = None, (0, 0)
    image_conns = [c for c in bag.connections if c.topic == report.image_topic]
    index = -1
    for conn, _, msg in track(bag.messages(image_conns), "keyframes", sum(int(c.msgcount) for c in image_conns)):
        index += 1
        report.messages_read += 1
        w = window_of.get(index)
        if w is None:
            continue
        img = _decode(conn, msg)
        report.decoded += 1
        h0, w0 = img.shape[:2]
        if (camera.width, camera.height) not in ((w0, h0), (0, 0)):
            raise DataError(f"{bag.path}: {report.camera_info_topic} is for {camera.width}x{camera.height} images but "
                            f"{report.image_topic} has {w0}x{h0}")
        sharp = grey_sharpness(img)
        if w not in best or sharp > best[w][0]:
            best[w] = (sharp, index, img)
        if index == posed[plan.windows[w][-1]].index:  # the window is complete: write its sharpest
            _, kept, img = best.pop(w)
            if camera.lens is not None:
                und = und or undistortion(camera.intrinsics, w0, h0, camera.lens)
                img = und.image(img)
            name, size = f"frame_{kept:06d}", (int(img.shape[1]), int(img.shape[0]))
            write_png(out / "images" / f"{name}.png", img)
            written.append({"file_path": f"images/{name}.png", "transform_matrix": matrix_to_list(c2w[pose_of[kept]]),
                            "stamp_ns": posed[pose_of[kept]].stamp, "sharpness": sharp})
    report.keyframes = len(written)
    intrinsics = und.intrinsics if und is not None else camera.intrinsics
    if und is not None:
        report.notes.append(f"lens distortion undone: {und.describe()}")
    write_json(out / "transforms.json", {
        "camera_model": "PINHOLE", "w": size[0], "h": size[1], **dict(zip(("fl_x", "fl_y", "cx", "cy"), intrinsics)),
        "dinerf": {"source": "ros2 bag", "fixed_frame": report.fixed_frame, "camera_frame": report.camera_frame},
        "frames": written})


def extract_keyframes(path: str | Path, out: str | Path, cfg: RosBagConfig | None = None) -> BagReport:
    """Read the bag at ``path`` and write its keyframes to ``out`` (a new folder) with ``bag.json``."""
    cfg = cfg or RosBagConfig()
    path, out = Path(path), Path(out)
    t0 = time.monotonic()
    bag = _Bag(path)
    try:
        report = BagReport(path=str(path), storage=_storage(path), topics=bag.topics())
        report.duration_s = bag.reader.duration * 1e-9 if bag.connections else 0.0
        report.image_topic, report.image_type = _choose_image_topic(bag, cfg)
        if not sum(int(c.msgcount) for c in bag.connections if c.topic == report.image_topic):
            raise DataError(f"{path}: the camera topic {report.image_topic} has no messages")
        report.camera_info_topic = _choose_info_topic(bag, cfg, report.image_topic)
        tf, camera, frames = _first_pass(bag, cfg, report)
        report.camera, report.images = camera.describe(), len(frames)
        report.lens = camera.lens.name if camera.lens is not None else ""
        posed, c2w = _poses(bag, cfg, tf, frames, report)
        _write_keyframes(bag, cfg, camera, posed, c2w, out, report)
    finally:
        bag.close()
    report.seconds = time.monotonic() - t0
    record = {"source": _fingerprint(path), "config": dataclasses.asdict(cfg), "report": report.to_dict()}
    write_json(out / BAG_RECORD, record)
    return report


def _storage(path: Path) -> str:
    if path.is_dir():
        files = [p.suffix for p in path.iterdir() if p.suffix in BAG_SUFFIXES]
        return "mcap" if ".mcap" in files else "sqlite3"
    return "mcap" if path.suffix.lower() == ".mcap" else "sqlite3"


def _fingerprint(path: Path) -> dict:
    """Which recording a keyframe folder came from: a bag that changed is read again."""
    files = sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]
    return {"path": str(path.resolve()), "files": [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in files]}


def load_bag(path: str | Path, *, width: int | None = None, cfg: RosBagConfig | None = None,
             cache_dir: str | Path | None = None) -> Views:
    """The bag's keyframes as :class:`Views` (at ``width``), through ``cache_dir`` when given.

    A cache made from the same recording is reused even when the settings changed since: a run's
    keyframes are its robot's views (its checkpoint's per-view state is sized by them), so they are
    kept for the life of the run folder, as an images-only robot keeps its SfM; the views' notes say
    so. Delete the folder to read the bag again."""
    from agent.data.transforms_json import load_transforms

    cfg = cfg or RosBagConfig()
    path = Path(path)
    if cache_dir is not None and _streamed(Path(cache_dir)):  # kept while the robot trained (up --replay)
        return load_transforms(Path(cache_dir) / "transforms.json", width=width, load_depth=False)
    if cache_dir is not None:
        cache = Path(cache_dir)
        record = _read_record(cache)
        if record is None or record.get("source") != _fingerprint(path):
            # read into a temporary folder first: a bag that cannot be read leaves nothing behind
            tmp = Path(tempfile.mkdtemp(prefix=".keyframes.", dir=cache.parent if cache.parent.is_dir() else None))
            try:
                extract_keyframes(path, tmp / "keyframes", cfg)
                if cache.exists():
                    shutil.rmtree(cache)
                cache.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(tmp / "keyframes"), str(cache))
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            record = _read_record(cache)
        views = load_transforms(cache / "transforms.json", width=width, load_depth=False)
        _describe(views, record, cfg)
        return views
    with tempfile.TemporaryDirectory(prefix="dinerf-bag-") as tmp:
        extract_keyframes(path, Path(tmp) / "keyframes", cfg)
        record = _read_record(Path(tmp) / "keyframes")
        views = load_transforms(Path(tmp) / "keyframes" / "transforms.json", width=width, load_depth=False)
    _describe(views, record, cfg)
    return views


def _streamed(folder: Path) -> bool:
    """Keyframes that agent.data.stream wrote as they arrived: the run's own, never read again from the bag."""
    try:
        return json.loads((folder / "transforms.json").read_text()).get("dinerf", {}).get("source") == "stream"
    except (OSError, ValueError, AttributeError):
        return False


def _read_record(folder: Path) -> dict | None:
    try:
        record = json.loads((folder / BAG_RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and (folder / "transforms.json").is_file() else None


def _describe(views: Views, record: dict | None, cfg: RosBagConfig) -> None:
    """``meta['format']``, ``meta['bag']`` (the report) and the notes ``inspect`` shows."""
    report = (record or {}).get("report", {})
    views.meta["format"] = "ros2 bag"
    views.meta["bag"] = report
    if report.get("lens"):  # undone when the keyframes were written: said as the image loaders say it
        views.meta["lens"] = {"models": [report["lens"]], "undistorted": True,
                              "done": "undistorted at load (OpenCV), pinhole intrinsics replaced"}
    notes = list(views.meta.get("notes", [])) + list(report.get("notes", []))
    if record is not None and record.get("config") != dataclasses.asdict(cfg):
        notes.append("keyframes kept from an earlier read of this bag with other data.ros settings (delete the "
                     "run folder's keyframes/ to read it again)")
        views.meta["bag_settings_changed"] = True
    views.meta["notes"] = notes
