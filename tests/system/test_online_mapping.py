"""`up --replay`: a robot trains while its bag plays at its recorded pace, its views growing round by round.

The bag is recorded here from the procedural scene (agent.data.ros.record) and played at 0.08x
its pace, every moving frame a keyframe (sharpness window 1): one every 1.25 s, so that some arrive
during the rounds on a fast machine too (with the default window of 5, one came every ~6 s, and a
fast machine trained all 5 rounds on the 3 it started from). The real `up` runs it; then it
is started again with one more round: it resumes with the keyframes it had, none added twice.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.data.loaders import load_views
from agent.data.ros.record import RecordConfig, bag_storage_file, record_bag
from agent.telemetry import read_events, read_telemetry

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow
SMALL = ["--set", "training.train.rays_per_step=512", "--set", "training.train.field.grid.log2_hashmap_size=12",
         "--set", "training.train.field.grid.num_levels=8", "--set", "training.train.field.density_hidden=32",
         "--set", "training.train.field.color_hidden=32", "--set", "training.train.occupancy.resolution=32",
         "--set", "training.own_holdout_every=4", "--set", "training.image_width=32",
         "--set", "data.stream.start_keyframes=3", "--set", "data.stream.capacity=64",
         "--set", "daemon.realign_every=1", "--set", "data.ros.keyframes.sharpness_window=1"]


def _up(tmp: Path, env: dict, *extra: str) -> tuple[int, str]:
    argv = [sys.executable, "-m", "cli", "up", "--id", "1", "--data", "robot1.mcap", "--swarm", "sw/swarm.toml",
            "--tls", "sw/robot1/tls", "--replay", "0.08", *SMALL, *extra]
    out = subprocess.run(argv, cwd=tmp, env=env, capture_output=True, text=True, timeout=400)
    return out.returncode, out.stdout + out.stderr


def test_a_replayed_bag_grows_the_views_while_the_robot_trains_and_a_restart_keeps_them(tmp_path):
    views = load_views("procedural:views=24,width=64")
    record_bag(views, tmp_path / "bag1", np.eye(4), RecordConfig())  # 10 Hz: 2.4 s, 30 s at 0.08x
    bag_storage_file(tmp_path / "bag1").rename(tmp_path / "robot1.mcap")
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1", COLUMNS="250")
    out = subprocess.run([sys.executable, "-m", "cli", "init", "--robots", "1", "--out", "sw", "--rounds", "5",
                          "--steps", "15"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    code, log = _up(tmp_path, env)
    assert code == 0, log
    run = tmp_path / "runs" / "sw" / "robot1"
    records = read_telemetry(run / "telemetry.jsonl")
    assert [r.round for r in records] == [1, 2, 3, 4, 5]
    counts = [r.keyframes for r in records]
    assert counts[0] < counts[-1] and counts == sorted(counts), (counts, log)  # the views grew while it trained
    assert all(r.coverage is not None and r.keyframe_age_s is not None for r in records)
    assert "keyframes" in log and "replaying" in log
    frames = json.loads((run / "keyframes" / "transforms.json").read_text())["frames"]
    held = sum(f["held_out"] for f in frames)
    assert len(frames) - held == counts[-1] and held == len(frames) // 4
    # every training keyframe is counted once (round 1's count includes those it started from)
    assert sum(r.keyframes_admitted for r in records) == counts[-1]
    # the keyframe summary it serves follows them (every round here: realign_every = 1), for robots still
    # unplaced: re-served after each round whose count changed, whatever the pace of replay against training
    served = [e for e in read_events(run / "events.jsonl") if e["event"] == "keyframes"]
    changes = sum(a != b for a, b in zip([served[0]["views"], *counts], counts))
    assert len(served) == 1 + changes and all(e.get("refreshed") for e in served[1:]), (served, counts)
    assert served[-1]["views"] == counts[-1] > served[0]["views"], (served, counts)
    code, log = _up(tmp_path, env, "--set", "training.rounds=6")
    assert code == 0, log
    assert "resumed" in log and read_telemetry(run / "telemetry.jsonl")[-1].round == 6
    again = json.loads((run / "keyframes" / "transforms.json").read_text())["frames"]
    assert again[:len(frames)] == frames and len({f["file_path"] for f in again}) == len(again)
    # eval reads the keyframes the run kept and its checkpoint (per-view state sized for the stream)
    out = subprocess.run([sys.executable, "-m", "cli", "eval", "runs/sw"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    # (the table's title wraps with the terminal's width: the line before it does not)
    assert out.returncode == 0 and "rendering each other's held-out frames" in out.stdout, out.stdout + out.stderr
