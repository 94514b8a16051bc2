"""Reading a robot's ROS 2 bag (issue 41): seconds per thousand messages, and memory that does not grow with it.

    .venv/bin/python benchmarks/bench_bags.py --out /tmp/bags        # 3 min at 30 Hz, 200 Hz tf, JPEG and raw

A robot's recording is written here with rosbags' writer (no data set needed): a camera at
``--rate`` Hz for ``--minutes`` minutes driving a loop with its camera on a mount, ``/tf`` at
``--tf-rate`` Hz, CameraInfo with every image; once as 640x480 JPEG CompressedImage (MCAP) and once
as raw 320x240 rgb8 Image (sqlite3). Each bag is then read by ``agent.data.ros.load_bag`` in a fresh
process (so its peak RSS is the reader's own), the keyframes written to a folder as a robot's run
folder keeps them. Printed per bag: messages, its size, seconds, seconds per thousand messages,
keyframes kept, images decoded, and the reader's peak RSS beside the bag's size.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402


def write_bag(path: Path, minutes: float, rate: float, tf_rate: float, compressed: bool, size: tuple[int, int],
              storage: str) -> int:
    """A loop of radius 3 in the odometry frame, the camera looking inward; returns the message count."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from agent.data.ros import messages as msg
    from agent.data.ros.record import mount_transform

    ts = msg.typestore()
    w_px, h_px = size
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 256, (h_px // 8, w_px // 4, 3), dtype=np.uint8), (2 * w_px, h_px),
                         interpolation=cv2.INTER_NEAREST)  # a panorama the camera pans across
    duration = minutes * 60
    t0 = 1_700_000_000.0
    count = 0
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        topic = "/camera/image_raw/compressed" if compressed else "/camera/image_raw"
        kind = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        c_img = w.add_connection(topic, kind, typestore=ts)
        c_info = w.add_connection("/camera/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
        static = msg.tf_message(msg.transform(t0, "base_link", "camera_optical", mount_transform(10.0)))
        w.write(c_static, int(t0 * 1e9), msg.serialize(static))
        events = sorted([(t0 + k / tf_rate, 0) for k in range(int(duration * tf_rate) + 2)]
                        + [(t0 + 0.5 / tf_rate + k / rate, 1) for k in range(int(duration * rate))])
        for i, (t, kind_index) in enumerate(events):
            angle = 2 * np.pi * (t - t0) / 60.0  # one loop a minute
            if kind_index == 0:  # base_link on the loop, facing its centre
                yaw = angle + np.pi
                m = np.eye(4)
                m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
                m[:2, 3] = 3 * np.cos(angle), 3 * np.sin(angle)
                w.write(c_tf, int(t * 1e9), msg.serialize(msg.tf_message(msg.transform(t, "odom", "base_link", m))))
            else:
                shift = int((angle / (2 * np.pi)) * w_px) % w_px
                px = np.ascontiguousarray(texture[:, shift:shift + w_px])
                if compressed:
                    _, buf = cv2.imencode(".jpg", px, [cv2.IMWRITE_JPEG_QUALITY, 90])
                    image = msg.compressed(t, buf.tobytes(), "jpeg")
                else:
                    image = msg.image(t, px, "rgb8")
                w.write(c_img, int(t * 1e9), msg.serialize(image))
                k = np.array([[0.8 * w_px, 0, w_px / 2], [0, 0.8 * w_px, h_px / 2], [0, 0, 1]])
                w.write(c_info, int(t * 1e9), msg.serialize(msg.camera_info(t, w_px, h_px, k)))
                count += 1
            count += 1
    return count + 1


def read_child(bag: str, out: str) -> None:
    """In a fresh process: read the bag into keyframes; print seconds, the report and the peak RSS."""
    from agent.data.ros import extract_keyframes

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # the interpreter, torch and rosbags loaded
    t = time.monotonic()
    report = extract_keyframes(bag, out)
    seconds = time.monotonic() - t
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"seconds": seconds, "messages": report.messages_read, "keyframes": report.keyframes,
                      "decoded": report.decoded, "images": report.images, "rss_mb": rss_mb, "rss_before_mb": rss0}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="a scratch folder (bags of a few hundred MB go there)")
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--tf-rate", type=float, default=200.0)
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        read_child(*args.child)
        return
    args.out.mkdir(parents=True, exist_ok=True)
    for name, compressed, size, storage in (("jpeg640", True, (640, 480), "mcap"), ("raw320", False, (320, 240), "sqlite3")):
        bag = args.out / name
        shutil.rmtree(bag, ignore_errors=True)
        t = time.monotonic()
        written = write_bag(bag, args.minutes, args.rate, args.tf_rate, compressed, size, storage)
        mb = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
        print(f"{name}: wrote {written} messages, {mb:.0f} MB in {time.monotonic() - t:.0f} s", flush=True)
        keyframes = args.out / f"{name}_keyframes"
        shutil.rmtree(keyframes, ignore_errors=True)
        child = subprocess.run([sys.executable, __file__, "--out", str(args.out), "--child", str(bag), str(keyframes)],
                               capture_output=True, text=True, check=True)
        r = json.loads(child.stdout.strip().splitlines()[-1])
        print(f"{name}: read in {r['seconds']:.1f} s = {1000 * r['seconds'] / written:.2f} s per thousand messages of "
              f"the bag ({r['messages']} read over both passes); {r['images']} images, {r['keyframes']} keyframes kept, {r['decoded']} decoded; peak RSS "
              f"{r['rss_mb']:.0f} MB ({r['rss_before_mb']:.0f} MB before reading) for a {mb:.0f} MB bag", flush=True)


if __name__ == "__main__":
    main()
