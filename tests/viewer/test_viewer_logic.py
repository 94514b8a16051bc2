"""The viewer's logic without a browser: run-folder layouts, frustums in frame g, renders, scheduling.

The browser end to end (a real run, the real server, headless Chromium): test_view_browser.py.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

import cli.main
from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box
from agent.geometry import box_from_center, sim3_from_params, transform_c2w
from agent.swarm import SwarmTrainingConfig, build_robot
from agent.telemetry import RoundRecord
from agent.viewer.scene import (PALETTE, RenderScheduler, c2w_from_browser, colour_of, frustums, home_view,
                                panel_markdown, render_at_camera)
from agent.runs import RobotRun
from agent.viewer.source import RobotStatus

cli.main._register()


def _telemetry(run_dir: Path, robot: int, rounds: int, **fields) -> None:
    run_dir.mkdir(parents=True)
    lines = [RoundRecord(robot=robot, round=k, **fields).to_json() for k in range(1, rounds + 1)]
    (run_dir / "telemetry.jsonl").write_text("\n".join(lines) + "\n")


def test_view_without_data_on_a_hand_run_swarm_that_does_not_record_it_is_one_line(tmp_path):
    _telemetry(tmp_path / "swarm1" / "robot3", 3, 1)  # an older dinerf's run dir: no data.json
    res = CliRunner().invoke(cli.main.app, ["view", str(tmp_path / "swarm1")])
    lines = res.stderr.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and "does not record its data folder" in lines[0], res.stderr
    assert "pass --data" in lines[0]


def test_status_reads_round_newest_psnr_and_frame(tmp_path):
    run = tmp_path / "robot2"
    _telemetry(run, 2, 3, alignment="unaligned")
    with open(run / "telemetry.jsonl", "a") as f:  # a PSNR at round 4, none at round 5, and a line cut by SIGKILL
        f.write(RoundRecord(robot=2, round=4, psnr=21.5, alignment="unaligned").to_json() + "\n")
        f.write(RoundRecord(robot=2, round=5, alignment="coarse").to_json() + "\n{\"robot\": 2, \"rou")
    status = RobotStatus.read(RobotRun(2, run, tmp_path))
    assert (status.round, status.psnr, status.psnr_round, status.frame, status.done) == (5, 21.5, 4, "coarse", False)
    text = panel_markdown([status], 2, 5, {2: PALETTE[0]}, {2: "checkpoint.safetensors: damaged"})
    assert "| 5 | 21.50 (round 4) | coarse |" in text and "damaged" in text and "round 5" in text
    _telemetry(tmp_path / "robot7", 7, 2, alignment="unaligned")
    assert RobotStatus.read(RobotRun(7, tmp_path / "robot7", tmp_path)).frame == "unaligned (out of consensus)"


@pytest.fixture(scope="module")
def posed_robot():
    """An untrained robot whose local frame sits 40 deg, a shift and a scale away from frame g."""
    views = load_views("procedural:views=6,width=16")
    centre, half, _ = estimate_scene_box(views)
    pose = sim3_from_params(torch.tensor(math.log(1.3)), torch.tensor([0.0, 0.0, math.radians(40)]),
                            torch.tensor([0.5, -0.2, 0.1])).float()
    cfg = SwarmTrainingConfig()
    return build_robot(1, views, box_from_center(centre, half), cfg, initial_pose=pose).trainer, pose


def test_frustums_are_the_cameras_in_the_shared_frame(posed_robot):
    trainer, pose = posed_robot
    shared = transform_c2w(pose, trainer.c2w_local).numpy()  # [M, 4, 4] OpenGL, frame g
    drawn = frustums(trainer, 1, PALETTE[1])
    assert len(drawn) == len(shared) and {f.colour for f in drawn} == {PALETTE[1]}
    for f, c2w in zip(drawn, shared):
        np.testing.assert_allclose(f.position, c2w[:3, 3], atol=1e-5)
        np.testing.assert_allclose(c2w_from_browser(np.array(f.wxyz), np.array(f.position)), c2w, atol=1e-5)
        fy = float(trainer.intrinsics[0, 1])
        assert f.fov_y == pytest.approx(2 * math.atan(16 / (2 * fy))) and f.aspect == 1.0
    home = home_view(trainer)  # looks at the field box's centre from further out than the cameras
    centre = np.array(home.look_at)
    assert np.linalg.norm(np.array(home.position) - centre) > np.linalg.norm(shared[0, :3, 3] - centre)
    assert colour_of(1) == PALETTE[0] and colour_of(3) == PALETTE[2] and colour_of(1 + len(PALETTE)) == PALETTE[0]


def test_render_at_a_training_camera_is_the_trainer_s_own_render(posed_robot):
    trainer, _ = posed_robot
    c2w = trainer.cameras_shared()[2].detach()
    fy = float(trainer.intrinsics[2, 1])
    fov = 2 * math.atan(16 / (2 * fy))
    image = render_at_camera(trainer, c2w.numpy(), fov, 1.0, 16)  # the view's own fov, centre and size
    own = trainer.render(c2w, trainer.intrinsics[2], 16, 16)["rgb"]
    assert image.shape == (16, 16, 3) and image.dtype == np.uint8
    np.testing.assert_allclose(image.astype(float), (own.clamp(0, 1) * 255).numpy(), atol=1.0)
    assert render_at_camera(trainer, c2w.numpy(), fov, 2.0, 32).shape == (16, 32, 3)  # H = W / aspect


def test_scheduler_renders_small_while_moving_then_sharp_once_still():
    s = RenderScheduler(moving_width=64, still_width=160, settle_s=0.3)
    assert s.next(0.0) == (160, (0, 0, 160))  # nothing on screen yet: a sharp first picture
    s.shown((0, 0, 160))
    assert s.next(1.0) is None  # nothing changed
    s.camera_moved(1.0)
    width, token = s.next(1.1)
    assert width == 64
    s.camera_moved(1.15)  # moved again during that render: its picture is already stale
    s.shown(token)
    width, token = s.next(1.2)
    assert width == 64
    s.shown(token)
    assert s.next(1.3) is None  # still settling: the small picture stays
    width, token = s.next(1.5)
    assert width == 160
    s.shown(token)
    assert s.next(2.0) is None
    s.model_changed()  # a new checkpoint: rendered again, sharp, at the same camera
    assert s.next(2.1)[0] == 160


@pytest.mark.parametrize("args, expected", [
    (["view", "/nonexistent/run"], "no such folder"),
    (["view", ".", "--width", "4"], "--width 4"),
    (["view", ".", "--poll", "0"], "--poll 0"),
])
def test_bad_view_arguments_are_one_line(args, expected):
    res = CliRunner().invoke(cli.main.app, args)
    lines = res.stderr.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and expected in lines[0], res.stderr
