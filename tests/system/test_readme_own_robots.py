"""The README's "Your own robots", run as written: two robots with their own ROS 2 bags, no split.

The bags are recorded here from the procedural scene, as robots record them (agent.data.ros.record):
robot 1 a lone ``.mcap`` file, robot 2 a sqlite3 rosbag2 folder, each in its own odometry frame with
a tilted camera, /tf between the images and a lens in CameraInfo. Then the README block's commands
run in order, with fewer rounds and a small field appended so that the test takes seconds. Each
robot must finish, its log must say where it placed its frame, a robot placed by the coarse step must
be within 2 deg of the offsets applied here, and `eval` must score without any truth.
"""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from agent.data.ros.record import RecordConfig, bag_storage_file, record_bag
from agent.data.split import SplitConfig, split_dataset
from agent.geometry import pose_error, random_rotation
from agent.telemetry import read_telemetry
from tests.system.harness import readme_commands, readme_env, run_robots

pytestmark = pytest.mark.slow
SMALL = ["--set", "training.train.rays_per_step=512", "--set", "training.train.field.grid.log2_hashmap_size=12",
         "--set", "training.train.field.grid.num_levels=8", "--set", "training.train.field.density_hidden=32",
         "--set", "training.train.field.color_hidden=32", "--set", "training.train.occupancy.resolution=32",
         "--set", "training.own_holdout_every=4", "--set", "training.image_width=32"]


def record(tmp: Path) -> dict[int, np.ndarray]:
    """robot1.mcap and robot2_bag/ in ``tmp``; returns each robot's T_odom_from_world."""
    _, split = split_dataset("procedural:views=40,width=96", SplitConfig(robots=2, frame="world", overlap=0.3,
                                                                          test_every=0), None)
    g = torch.Generator().manual_seed(7)
    offsets = {}
    for i, storage in ((1, "mcap"), (2, "sqlite3")):
        offsets[i] = np.eye(4)
        offsets[i][:3, :3] = random_rotation(g).double().numpy()
        offsets[i][:3, 3] = torch.randn(3, generator=g).double().numpy()
        record_bag(split.robots[i].views, tmp / f"bag{i}", offsets[i], RecordConfig(storage=storage, k1=0.03))
    bag_storage_file(tmp / "bag1").rename(tmp / "robot1.mcap")
    (tmp / "bag2").rename(tmp / "robot2_bag")
    return offsets


def test_the_readme_own_robots_from_bags_to_a_score_without_truth(tmp_path):
    commands = readme_commands("Your own robots")
    kinds = [shlex.split(c)[1] for c in commands]
    assert kinds == ["init", "inspect", "up", "up", "eval"], kinds
    offsets = record(tmp_path)
    env = readme_env()

    def argv(command: str) -> list[str]:
        args = shlex.split(command)[1:]
        if args[0] == "init":  # a few short rounds instead of the README's
            args[args.index("--rounds") + 1], args[args.index("--steps") + 1] = "3", "10"
        return [sys.executable, "-m", "cli", *args] + (SMALL if args[0] == "up" else [])

    init, inspect, ups, evaluate = commands[0], commands[1], commands[2:4], commands[4]
    out = subprocess.run(argv(init), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "--tls myswarm/robot1/tls" in out.stdout or "robot 1" in out.stdout
    out = subprocess.run(argv(inspect), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "odom -> base_link -> camera_optical" in out.stdout, out.stdout + out.stderr
    codes, text = run_robots({i: argv(c) for i, c in zip((1, 2), ups)}, tmp_path, env, timeout=300)
    assert codes == {1: 0, 2: 0}, text
    runs = tmp_path / "runs" / "myswarm"
    for i in (1, 2):
        assert (runs / f"robot{i}" / "keyframes" / "transforms.json").is_file()
        last = read_telemetry(runs / f"robot{i}" / "telemetry.jsonl")[-1]
        assert "pose est" in text[i] and last.round == 3
        if last.alignment == "coarse":  # placed: the pose found must be the offsets applied
            truth = offsets[1] @ np.linalg.inv(offsets[i])  # robot i's odometry -> robot 1's (the shared frame)
            err = pose_error(torch.tensor(last.pose, dtype=torch.float64), torch.from_numpy(truth))
            assert err["rotation_deg"] < 2.0, (err, text[i])
        else:
            assert last.alignment in ("reference", "unaligned") and ("UNALIGNED" in text[i]) == (last.alignment == "unaligned")
    out = subprocess.run(argv(evaluate), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr
    assert "own held-out frames" in out.stdout and "relative poses found" in out.stdout, out.stdout
