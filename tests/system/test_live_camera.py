"""A robot's live camera over Zenoh, as rmw_zenoh carries it, into the robot's view stream.

A real Zenoh router stands for the robot's rmw_zenohd; a separate process publishes a bag's camera,
CameraInfo, /tf and /tf_static on rmw_zenoh's keys (tools/rmw_zenoh_publish.py); the stream
subscribes as ``up --live`` does (cli/view_source.py), poses each image from tf, keeps keyframes.
The publisher stops half way and comes back as a new process: nothing received is lost, nothing
is added twice, and every keyframe has the pose the bag loader gives it.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from agent.data.config import DataConfig
from agent.data.ros import RosBagConfig, extract_keyframes
from agent.data.ros.config import KeyframeConfig
from agent.data.stream import StreamConfig
from agent.swarm import SwarmTrainingConfig
from cli.view_source import open_stream
from protocol.ros_camera import open_router
from tests.data.bags import camera_bag
from tests.protocol.helpers import free_port

ROOT = Path(__file__).resolve().parents[2]


def _publish(bag: Path, endpoint: str, **kw) -> None:
    cmd = [sys.executable, str(ROOT / "tools" / "rmw_zenoh_publish.py"), str(bag), "--connect", endpoint,
           "--mode", "client", "--rate", "4", "--match-timeout", "3"]
    cmd += [a for k, v in kw.items() for a in (f"--{k}", str(v))]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr


def test_live_frames_become_posed_keyframes_and_a_restarted_camera_loses_nothing(tmp_path):
    bag = camera_bag(tmp_path / "bag", n=16, moves=0.5)
    ros = RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1, max_keyframes=0))
    cfg = SimpleNamespace(data=DataConfig(ros=ros, stream=StreamConfig(start_timeout_s=20, capacity=100)),
                          training=SwarmTrainingConfig(own_holdout_every=4))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])
    source = open_stream(cfg, tmp_path / "robot", tmp_path / "run" / "keyframes", None, [endpoint], print)
    stream = source.stream
    try:
        _publish(bag, endpoint, count=90)
        stream.wait_for_start()
        before = [dict(f) for f in stream.store.frames]
        assert 3 <= len(before) < 16
        _publish(bag, endpoint, skip=90)  # the camera driver restarted: a new gid, its sequence from 1
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(stream.store.frames) < 15:
            stream.admit()
            time.sleep(0.1)
        stream.admit()
    finally:
        source.close()
        router.close()
    frames = stream.store.frames
    assert frames[:len(before)] == before  # what the robot had is kept as it was
    names = [f["file_path"] for f in frames]
    assert len(names) == len(set(names)) >= 15  # nothing twice; at most the last window still open
    assert [f["held_out"] for f in frames] == [i % 4 == 3 for i in range(len(frames))]
    extract_keyframes(bag, tmp_path / "offline", RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1)))
    offline = {f["file_path"]: f["transform_matrix"]
               for f in json.loads((tmp_path / "offline" / "transforms.json").read_text())["frames"]}
    for f in frames:  # posed from /tf and /tf_static received over Zenoh as the bag loader poses them
        np.testing.assert_allclose(f["transform_matrix"], offline[f["file_path"]], atol=1e-6)
    assert (tmp_path / "run" / "keyframes" / frames[-1]["file_path"]).is_file()
    assert source.subscriber.refused == {} and source.subscriber.duplicates == 0
