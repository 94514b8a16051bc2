"""A robot's own camera over Zenoh in rmw_zenoh's format: keys, attachment, and a real session.

The publisher is a separate process (tools/rmw_zenoh_publish.py) writing a bag the test wrote;
the router is a real Zenoh router; the subscriber connects to it as a client, as the daemon does.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from protocol.rmw_format import (Attachment, AttachmentError, dds_type_name, parse_topic_key, ros_type_name,
                                 topic_key, topic_key_pattern)
from protocol.ros_camera import RosTopicSubscriber, open_router, type_hash
from tests.data.bags import T0, camera_bag
from tests.protocol.helpers import free_port

ROOT = Path(__file__).resolve().parents[2]
TOPICS = [("/camera/image_raw", "sensor_msgs/msg/Image"), ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
          ("/tf", "tf2_msgs/msg/TFMessage"), ("/tf_static", "tf2_msgs/msg/TFMessage")]


def test_keys_are_rmw_zenohs():
    h = type_hash("sensor_msgs/msg/Image")
    assert h.startswith("RIHS01_") and len(h) == 7 + 64
    key = topic_key(0, "/camera/image_raw", "sensor_msgs/msg/Image", h)
    assert key == f"0/camera/image_raw/sensor_msgs::msg::dds_::Image_/{h}"
    assert parse_topic_key(key) == (0, "/camera/image_raw", "sensor_msgs/msg/Image", h)
    assert topic_key_pattern(3, "/tf", "tf2_msgs/msg/TFMessage") == "3/tf/tf2_msgs::msg::dds_::TFMessage_/*"
    assert ros_type_name(dds_type_name("tf2_msgs/msg/TFMessage")) == "tf2_msgs/msg/TFMessage"
    for bad in ("camera", "0/camera/Image/x", "x/camera/sensor_msgs::msg::dds_::Image_/h"):
        with pytest.raises(ValueError):
            parse_topic_key(bad)
    with pytest.raises(ValueError):
        topic_key(0, "camera/no_slash", "sensor_msgs/msg/Image", h)


def test_attachment_round_trip_and_refusals():
    a = Attachment(7, 1_700_000_000_123_456_789, bytes(range(16)))
    raw = a.encode()
    assert len(raw) == 33 and raw[16] == 16  # int64, int64, LEB128 length 16, 16 bytes
    assert Attachment.decode(raw) == a
    for bad in (None, b"", raw[:-1], raw + b"x", raw[:16] + b"\x0f" + raw[17:]):
        with pytest.raises(AttachmentError):
            Attachment.decode(bad)


def _publish(bag: Path, endpoint: str, *, skip: int = 0, count: int | None = None) -> int:
    cmd = [sys.executable, str(ROOT / "tools" / "rmw_zenoh_publish.py"), str(bag), "--connect", endpoint,
           "--mode", "client", "--rate", "0", "--skip", str(skip), "--match-timeout", "3"]
    if count is not None:
        cmd += ["--count", str(count)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[1])


def _wait(cond, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not cond():
        time.sleep(0.05)
    return cond()


def test_a_restarted_publisher_loses_nothing_the_robot_had(tmp_path):
    bag = camera_bag(tmp_path / "bag", n=12, w=16, h=12)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])
    got, lock = [], threading.Lock()

    def on_message(m):
        with lock:
            got.append(m)

    sub = RosTopicSubscriber([endpoint], TOPICS, on_message).open()
    try:
        first = _publish(bag, endpoint, count=60)  # the driver stops mid-run ...
        assert _wait(lambda: len(got) >= first)
        images_before = [m for m in list(got) if m.topic == "/camera/image_raw"]
        total = first + _publish(bag, endpoint, skip=60)  # ... and comes back as a new process
        assert _wait(lambda: len(got) >= total)
        time.sleep(0.3)
    finally:
        sub.close()
        router.close()
    images = [m for m in got if m.topic == "/camera/image_raw"]
    stamps = [m.message.header.stamp.sec + m.message.header.stamp.nanosec * 1e-9 for m in images]
    assert len(images) == 12 and stamps == pytest.approx([T0 + 0.1 * i for i in range(12)], abs=1e-6)
    assert images[:len(images_before)] == images_before  # what was received before the stop is kept as it was
    assert len({m.attachment.gid for m in images}) == 2  # two processes, two publishers
    assert images[0].message.encoding == "rgb8" and len(images[0].message.data) == 16 * 12 * 3
    assert any(m.topic == "/tf_static" for m in got) and sum(m.topic == "/tf" for m in got) > 50
    assert sub.refused == {} and sub.duplicates == 0
    assert len(got) == total


def test_what_is_not_rmw_zenohs_is_refused_by_reason(tmp_path):
    import zenoh

    from protocol.ros_camera import _client_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])
    got = []
    sub = RosTopicSubscriber([endpoint], TOPICS, got.append).open()
    hostile = zenoh.open(_client_config([endpoint]))
    try:
        h = type_hash("sensor_msgs/msg/Image")
        key = topic_key(0, "/camera/image_raw", "sensor_msgs/msg/Image", h)
        good = Attachment(1, 0, bytes(16)).encode()
        time.sleep(0.5)
        hostile.put(key, b"\x00\x01\x00\x00" + b"\xff" * 7)  # no attachment
        hostile.put(key, b"\x00\x01\x00\x00", attachment=b"short")
        hostile.put(key, b"\x00\x01\x00\x00garbage", attachment=good)  # not an Image in CDR
        hostile.put(key.replace(h, "RIHS01_" + "0" * 64), b"", attachment=Attachment(2, 0, bytes(16)).encode())
        assert _wait(lambda: sum(sub.refused.values()) >= 4)
    finally:
        hostile.close()
        sub.close()
        router.close()
    assert got == [] and sub.refused == {"bad_attachment": 2, "bad_cdr": 1, "type_hash": 1}
