"""Wrong inputs to the commands: each is one line ``error: ...`` and exit code 2, never a traceback.

In process (typer's runner: the commands' own code, without a fresh interpreter per case); every
case fails before any training or network starts. Checkpoints that are directories, pickles or
damaged: tests/system/test_hostile_checkpoint.py (``up`` in a subprocess: it opens Zenoh).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

import cli.main

cli.main._register()
runner = CliRunner()
TINY = "procedural:views=8,width=8"


def _fails_in_one_line(args: list[str], *expected: str) -> str:
    res = runner.invoke(cli.main.app, [str(a) for a in args])
    assert not (res.exception and not isinstance(res.exception, SystemExit)), f"a traceback: {res.exception!r}"
    lines = res.stderr.strip().splitlines()
    assert res.exit_code == 2, (res.exit_code, res.stdout[-500:], res.stderr[-500:])
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    for text in expected:
        assert text in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def split(tmp_path_factory) -> Path:
    """A tiny split (robot1/, robot2/, swarm.toml)."""
    out = tmp_path_factory.mktemp("cli") / "split"
    res = runner.invoke(cli.main.app, ["split", "--data", "procedural:views=12,width=16", "-n", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture
def junk(tmp_path) -> dict[str, Path]:
    files = {"binary": b"\x00\xff\xfe\x01binary", "latin1": 'name = "caf\xe9"\n'.encode("latin-1"), "text": b"hello\n"}
    out = {}
    for name, data in files.items():
        out[name] = tmp_path / f"{name}.toml"
        out[name].write_bytes(data)
    (tmp_path / "folder").mkdir()
    out["folder"] = tmp_path / "folder"
    return out


@pytest.mark.parametrize("kind", ["binary", "latin1"])
def test_a_swarm_or_config_file_that_is_not_utf8_text(split, junk, kind):
    _fails_in_one_line(["up", "--id", 1, "--data", split / "robot1", "--swarm", junk[kind]], "not UTF-8")
    _fails_in_one_line(["baseline", "--data", TINY, "--config", junk[kind]], "not UTF-8")
    _fails_in_one_line(["scenario", "run", junk[kind]], "not UTF-8")


@pytest.mark.parametrize("override, key", [
    ("training.train.rays_per_step=0", "training.train.rays_per_step must be >= 1, got 0"),
    ("training.train.min_rays_per_step=-3", "training.train.min_rays_per_step must be >= 1"),
    ("training.train.occupancy.resolution=0", "training.train.occupancy.resolution must be >= 1"),
    ("training.train.occupancy.update_every=0", "training.train.occupancy.update_every must be >= 1"),
    ("training.train.occupancy.decay=1.5", "training.train.occupancy.decay must be in [0, 1]"),
    ("training.train.march.step_size=0", "training.train.march.step_size must be > 0"),
    ("training.train.march.early_stop_eps=0", "training.train.march.early_stop_eps must be in (0, 1)"),
    ("training.train.march.far=-1", "training.train.march.far must be > near"),
    ("training.train.field.density_hidden=0", "training.train.field.density_hidden must be >= 1"),
    ("training.train.field.grid.features_per_level=0", "training.train.field.grid.features_per_level must be >= 1"),
    ("training.train.field.grid.max_resolution=4", "training.train.field.grid.max_resolution must be >= base_resolution"),
    ("training.train.optim.lr=-0.01", "training.train.optim.lr must be > 0"),
    ("training.train.optim.lr=nan", "training.train.optim.lr must be > 0, got nan"),
    ("training.train.optim.eps=0", "training.train.optim.eps must be > 0"),
    ("training.train.optim.betas=[0.9, 1.0]", "training.train.optim.betas[1] must be in [0, 1)"),
    ("training.train.optim.decay_at=[0.5, 2]", "training.train.optim.decay_at[1] must be in [0, 1]"),
    ("training.train.pose.lr_rotation=-1", "training.train.pose.lr_rotation must be >= 0"),
    ("training.train.pose.decay_to=0", "training.train.pose.decay_to must be in (0, 1]"),
    ("training.train.device='gpu9'", "training.train.device is not a torch device"),
])
def test_a_size_or_rate_that_would_crash_or_train_nothing_names_its_key(split, override, key):
    _fails_in_one_line(["up", "--id", 1, "--data", split / "robot1", "--set", override], key)


def test_baseline_checks_its_numbers_and_its_output_folder(tmp_path, junk):
    _fails_in_one_line(["baseline", "--data", TINY, "--set", "rays_per_step=0"], "rays_per_step must be >= 1, got 0")
    _fails_in_one_line(["baseline", "--data", TINY, "--steps", 0], "--steps must be >= 1")
    _fails_in_one_line(["baseline", "--data", TINY, "--out", junk["text"]], "exists and is not a folder")
    _fails_in_one_line(["baseline", "--data", TINY, "--out", junk["text"] / "sub"], "Not a directory")
    _fails_in_one_line(["baseline", "--data", TINY, "--config", junk["folder"]], "config file not found")


def test_a_file_where_a_folder_is_expected_and_a_missing_folder(split, junk, tmp_path):
    _fails_in_one_line(["up", "--id", 1, "--data", junk["text"]], "not a folder or a ROS 2 bag file")
    _fails_in_one_line(["up", "--id", 1, "--data", tmp_path / "absent"], "no such file or folder")
    _fails_in_one_line(["up", "--id", 1, "--data", split / "robot1", "--run-dir", junk["text"]],
                       "--run-dir", "exists and is not a folder")
    _fails_in_one_line(["scenario", "run", "quickstart", "--out", junk["text"]], "--out", "exists and is not a folder")
    _fails_in_one_line(["split", "--data", split / "robot1", "--out", junk["text"]], "exists and is not a folder")
    _fails_in_one_line(["inspect", "--data", tmp_path / "absent"], "no such file or folder")
    _fails_in_one_line(["scenario", "report", tmp_path / "absent"], "no run.json")


def test_an_image_that_is_not_an_image_and_a_json_file_that_is_not_json(split, tmp_path):
    import shutil

    robot = tmp_path / "robot1"
    shutil.copytree(split / "robot1", robot)
    first = sorted((robot / "images").iterdir())[0]
    first.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    for cmd in (["inspect"], ["split", "--out", tmp_path / "o"], ["baseline", "--out", tmp_path / "b"]):
        _fails_in_one_line([cmd[0], "--data", robot, *cmd[1:]], f"{first}: cannot be read as an image")
    images = tmp_path / "images_only" / "images"
    images.mkdir(parents=True)
    cv2.imwrite(str(images / "a.png"), np.zeros((8, 8, 3), np.uint8))
    (images / "b.png").write_bytes(b"GIF89a")
    _fails_in_one_line(["inspect", "--data", images.parent], "b.png: cannot be read as an image")
    (robot / "transforms.json").write_bytes(b"\xff\xfe{")
    _fails_in_one_line(["inspect", "--data", robot], "transforms.json: not valid JSON")
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_bytes(b"{")
    _fails_in_one_line(["scenario", "report", run], "run.json: not valid JSON")
    (run / "report.json").write_bytes(b"\xff")
    _fails_in_one_line(["scenario", "compare", run, "--fault-free", run], "report.json: not valid JSON")


def test_a_procedural_scene_too_large_for_memory_is_refused():
    _fails_in_one_line(["inspect", "--data", "procedural:views=4,width=100000"], "would not fit in memory")



@pytest.mark.slow  # a fresh interpreter: OpenCV and COLMAP write to the process's stderr, which the runner does not see
def test_opencv_and_colmap_add_no_lines_of_their_own_to_the_error(tmp_path):
    import os
    import subprocess
    import sys

    images = tmp_path / "robot" / "images"
    images.mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(images / f"{i}.png"), np.full((16, 16, 3), 40 * i, np.uint8))  # nothing to match
    bad = tmp_path / "bad" / "images"
    bad.mkdir(parents=True)
    (bad / "a.png").write_bytes(b"GIF89a")
    root = Path(__file__).resolve().parents[2]
    for folder, expected in ((images.parent, "SfM registered 0 of 3 images"), (bad.parent, "cannot be read as an image")):
        res = subprocess.run([sys.executable, "-m", "cli", "inspect", "--data", str(folder)], cwd=root,
                             capture_output=True, text=True, timeout=120, env=dict(os.environ, OMP_NUM_THREADS="1"))
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and expected in lines[0], res.stderr


def test_security_mistakes_and_the_cert_command(split, tmp_path):
    """A robot started with another's certificate folder, a revoked robot, tcp/ in a secure swarm,
    a CA folder that is not one: one line each. Issue and revoke work, and say what comes next."""
    import shutil

    _fails_in_one_line(["up", "--id", 2, "--data", split / "robot2", "--listen", "tcp/127.0.0.1:9"], "is not tls/")
    other = tmp_path / "robot2"
    shutil.copytree(split / "robot2", other)
    shutil.rmtree(other / "tls")
    shutil.copytree(split / "robot1" / "tls", other / "tls")
    _fails_in_one_line(["up", "--id", 2, "--data", other, "--swarm", split / "swarm.toml"],
                       "certificate of 'robot-1', not of 'robot-2'")
    _fails_in_one_line(["cert", "issue", "--ca", split / "robot1" / "tls", "--id", 3, "--out", tmp_path / "t"], "no ca.key")
    _fails_in_one_line(["cert", "issue", "--ca", split / "ca", "--out", tmp_path / "t"], "either --id")
    res = runner.invoke(cli.main.app, ["cert", "issue", "--ca", str(split / "ca"), "--id", "3", "--out", str(tmp_path / "r3")])
    assert res.exit_code == 0 and "issued robot-3" in res.stdout, res.output
    assert not (tmp_path / "r3" / "ca.key").exists()
    swarm = tmp_path / "swarm.toml"
    shutil.copy(split / "swarm.toml", swarm)
    shutil.copy(split / "scene.json", tmp_path / "scene.json")
    res = runner.invoke(cli.main.app, ["cert", "revoke", "--swarm", str(swarm), "--id", "2"])
    assert res.exit_code == 0 and "no revocation list" in res.stdout, res.output
    _fails_in_one_line(["up", "--id", 2, "--data", split / "robot2", "--swarm", swarm], "robot 2 is revoked")
    _fails_in_one_line(["cert", "issue", "--ca", split / "ca", "--id", 2, "--out", tmp_path / "r2", "--swarm", swarm],
                       "robot-2 is revoked")


def test_a_bag_that_cannot_give_views_is_one_line_and_leaves_no_run_folder(tmp_path):
    from tests.data import bags

    def bag(name: str, **kw) -> Path:
        return bags.camera_bag(tmp_path / name, n=4, **kw)

    truncated = bags.camera_bag(tmp_path / "whole", n=4, storage="mcap")
    mcap = next(truncated.glob("*.mcap"))
    (tmp_path / "cut.mcap").write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    db3 = next(bags.camera_bag(tmp_path / "whole_db", n=4, storage="sqlite3").glob("*.db3"))
    (tmp_path / "cut_db").mkdir()
    (tmp_path / "cut_db" / "cut.db3").write_bytes(db3.read_bytes()[:4096])
    two = bag("two", seed=1)
    other = bags.write_bag(tmp_path / "two_cams", [
        (topic, "sensor_msgs/msg/Image", bags.T0, bags.image(bags.T0, np.zeros((4, 4, 3), np.uint8), "rgb8"))
        for topic in ("/left/image_raw", "/right/image_raw")])
    empty = bags.write_bag(tmp_path / "empty", [("/tf", "tf2_msgs/msg/TFMessage", bags.T0, bags.tf_message(
        bags.transform(bags.T0, "odom", "base_link", np.eye(4))))], empty_topics=(("/camera/image_raw", "sensor_msgs/msg/Image"),))
    cases = {
        tmp_path / "cut.mcap": "truncated, damaged or not a bag",
        tmp_path / "cut_db" / "cut.db3": "not a readable rosbag2",
        bag("bayer", encoding="bayer_rggb8"): "/camera/image_raw: image encoding 'bayer_rggb8' is not supported",
        bag("no_link", image_frame="camera_on_arm"): "missing tf link",
        bag("zeros", info={"k": (0.0, 0.0, 0.0, 0.0)}): "no usable intrinsics",
        bag("no_tf", tf=False): "no /tf or /tf_static",
        bag("clock", tf_offset_s=3600.0): "clock mismatch",
        empty: "/camera/image_raw has no messages",
        other: "2 cameras",
        tmp_path / "missing.mcap": "no such",
    }
    assert two.is_dir()
    for path, text in cases.items():
        _fails_in_one_line(["inspect", "--data", path], text)
    swarm = tmp_path / "swarm"
    assert runner.invoke(cli.main.app, ["init", "--robots", "1,2", "--out", str(swarm)]).exit_code == 0
    run_dir = tmp_path / "runs" / "robot1"
    for path, text in list(cases.items())[:3]:
        _fails_in_one_line(["up", "--id", 1, "--data", path, "--swarm", swarm / "swarm.toml", "--tls",
                            swarm / "robot1" / "tls", "--run-dir", run_dir], text)
        assert not (tmp_path / "runs").exists()  # nothing written: no run folder, no keyframes


def test_up_replay_and_live_refuse_what_they_cannot_play(split, tmp_path):
    from tests.data.bags import camera_bag

    robot1, swarm = split / "robot1", split / "swarm.toml"
    _fails_in_one_line(["up", "--id", 1, "--data", robot1, "--replay", 1.0], "is not a ROS 2 bag")
    _fails_in_one_line(["up", "--id", 1, "--data", robot1, "--replay", 1.0, "--live", "tcp/127.0.0.1:9"],
                       "does not go with --live")
    bag = camera_bag(tmp_path / "bag")
    _fails_in_one_line(["up", "--id", 1, "--data", bag, "--swarm", swarm, "--tls", robot1 / "tls", "--replay", -1,
                        "--run-dir", tmp_path / "run1"], "must be >= 0")
    _fails_in_one_line(["up", "--id", 1, "--data", robot1, "--live", "tcp/127.0.0.1:9", "--run-dir", tmp_path / "run2",
                        "--set", "data.stream.start_timeout_s=1"], "no Zenoh router answered at tcp/127.0.0.1:9")
    from protocol.ros_camera import open_router
    from tests.protocol.helpers import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])  # a router, but no camera behind it
    try:
        _fails_in_one_line(["up", "--id", 1, "--data", robot1, "--live", endpoint, "--run-dir", tmp_path / "run3",
                            "--set", "data.stream.start_timeout_s=1"], "no keyframe arrived within 1 s")
    finally:
        router.close()
