"""Scenarios whose robots have images only: what the spec demands, the split at two widths, and the
evaluation's side (frames calibrated before scoring, "alone" in a calibrated frame), and the markdown."""

from __future__ import annotations

import dataclasses

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

import agent.evaluation.run
from agent.data.folder import read_truth
from agent.data.loaders import load_views
from agent.data.split import split_views
from agent.data.views import Views
from agent.evaluation import AloneScores, EvalSet, calibrate_frames, train_alone
from agent.geometry import random_rotation, sim3_inverse, transform_c2w
from cli.config import ConfigError
from cli.scenario import report as report_mod
from cli.scenario.runner import prepare_split
from cli.scenario.spec import find_scenario, load_scenario
from tests.data.helpers import LEGO

BASE = """
[scenario]
name = "io"
dataset = "procedural:views=24,width=48"
width = 24
robots = 2
[split]
overlap = 0.2
frame = "offset"
test_every = 6
images_only = true
robot_image_width = 48
[training]
rounds = 1
steps_per_round = 4
own_holdout_every = 0
image_width = 24
[training.train]
rays_per_step = 64
[training.train.pose]
mode = "sim3"
[training.train.field]
density_hidden = 16
color_hidden = 16
[training.train.field.grid]
log2_hashmap_size = 10
num_levels = 4
max_resolution = 32
[training.train.occupancy]
resolution = 16
[daemon]
initial_pose = "coarse"
[report]
ssim = false
"""


def spec_from(tmp_path: Path, text: str = BASE):
    p = tmp_path / "scenario.toml"
    p.write_text(text)
    return load_scenario(p)


def error(tmp_path: Path, text: str) -> str:
    with pytest.raises(ConfigError) as e:
        spec_from(tmp_path, text)
    return str(e.value)


def test_spec_demands_what_images_only_robots_need(tmp_path):
    s = spec_from(tmp_path)
    assert s.split.images_only and s.split.robot_image_width == 48
    assert s.split.images_only
    assert 'initial_pose = "coarse"' in error(tmp_path, BASE.replace('initial_pose = "coarse"', 'initial_pose = "identity"'))
    # unset, the frames decide: SfM frames start from the coarse alignment
    assert spec_from(tmp_path, BASE.replace('[daemon]\ninitial_pose = "coarse"\n', "")).daemon.initial_pose == "coarse"
    assert 'mode = "sim3"' in error(tmp_path, BASE.replace('mode = "sim3"', 'mode = "se3"'))
    assert ">= scenario.width" in error(tmp_path, BASE.replace("robot_image_width = 48", "robot_image_width = 16"))
    assert "needs scenario.width" in error(tmp_path, BASE.replace("width = 24\nrobots", "robots"))
    assert "depth_prior" in error(tmp_path, BASE.replace("images_only = true", 'images_only = true\ndepth_prior = "true"'))
    # a bigger robot width alone (known poses) is fine, and needs neither coarse nor sim3
    s = spec_from(tmp_path, BASE.replace("images_only = true", "images_only = false")
                  .replace('mode = "sim3"', 'mode = "se3"').replace('initial_pose = "coarse"', 'initial_pose = "identity"'))
    assert not s.split.images_only


def test_shipped_images_only_scenario():
    s = load_scenario(find_scenario("lego-2-images-only"))
    assert s.split.images_only and s.split.robot_image_width == 400 and s.width == 100
    assert s.training.image_width == 100 and s.training.train.pose.mode == "sim3"
    assert s.daemon.initial_pose == "coarse" and s.baseline.enabled


def test_prepare_split_writes_robots_wide_and_eval_at_the_scenario_width(tmp_path):
    spec = spec_from(tmp_path)
    summary = prepare_split(spec, tmp_path / "data")
    data = tmp_path / "data"
    assert summary["resolution"] == [24, 24] and summary["robot_resolution"] == [48, 48]
    truth = read_truth(data)
    split = json.loads((data / "split.json").read_text())
    for rid in (1, 2):
        folder = data / f"robot{rid}"
        assert not (folder / "transforms.json").exists(), "images only: no poses in a robot folder"
        names = sorted(p.stem for p in (folder / "images").glob("*.png"))
        assert names == sorted(split["robots"][str(rid)]["views"]) == sorted(truth["robots"][str(rid)]["cameras_world"])
        img = cv2.imread(str(next((folder / "images").glob("*.png"))), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (48, 48)
    ev = load_views(data / "eval")
    assert (ev.width, ev.height) == (24, 24) and len(ev) == summary["eval_views"] == 4
    # the same split (views, held-out views) as at the scenario's width: it depends on the poses only
    narrow = split_views(load_views(spec.resolved_dataset(), width=24), dataclasses.replace(spec.split, robots=2))
    assert ev.names == narrow.eval_views.names
    assert torch.allclose(ev.intrinsics, narrow.eval_views.intrinsics)
    for rid in (1, 2):
        assert split["robots"][str(rid)]["views"] == narrow.robots[rid].views.names
    assert json.loads((data / "scene.json").read_text())["box_from_shared"] is None


def _sim3(seed: int, scale: float) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = scale * random_rotation(gen)
    out[:3, 3] = torch.randn(3, generator=gen, dtype=torch.float64)
    return out


SFM = {1: _sim3(21, 0.3), 2: _sim3(22, 2.5)}  # each robot's SfM frame <- world


def _fake_sfm(truth: dict):
    """An ``agent.data.sfm`` whose run_sfm returns the true cameras in a per-robot Sim(3) frame."""

    def run_sfm(image_dir, cache_dir=None, *, width=None) -> Views:
        rid = int(Path(image_dir).name.removeprefix("robot"))
        cams = truth["robots"][str(rid)]["cameras_world"]
        files = sorted((Path(image_dir) / "images").glob("*.png"))
        imgs = [cv2.cvtColor(cv2.imread(str(f), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA) for f in files]
        if width is not None:
            imgs = [cv2.resize(im, (width, width), interpolation=cv2.INTER_AREA) for im in imgs]
        w = imgs[0].shape[1]
        world = torch.tensor([cams[f.stem] for f in files], dtype=torch.float64)
        return Views(torch.from_numpy(np.stack(imgs).astype(np.float32) / 255), transform_c2w(SFM[rid], world).float(),
                     torch.tensor([[w * 1.2, w * 1.2, w / 2, w / 2]] * len(files)), [f.stem for f in files])

    return SimpleNamespace(run_sfm=run_sfm)


def test_report_calibrates_frames_and_trains_alone_in_them(tmp_path, monkeypatch):
    spec = spec_from(tmp_path)
    out = tmp_path / "run"
    prepare_split(spec, out / "data")
    truth = json.loads((out / "data/truth.json").read_text())
    monkeypatch.setitem(sys.modules, "agent.data.sfm", _fake_sfm(truth))

    # the evaluation's calibration, on the cameras of the trainers load_for_eval rebuilds
    def fake_load_for_eval(run_dir, data_dir, round=None):
        views = load_views(data_dir, width=24)
        return SimpleNamespace(views=views, refined_views=lambda: views)  # cameras as trained (no refinement)

    monkeypatch.setattr(agent.evaluation.run, "load_for_eval", fake_load_for_eval)
    run = report_mod.swarm_run(out, spec.ids)
    evalset = EvalSet.from_dir(out / "data")
    notes = calibrate_frames(evalset, run, {1: [0], 2: []}, echo=lambda _: None)
    assert torch.allclose(evalset.T_world_from_local[1], sim3_inverse(SFM[1]), atol=1e-5)
    assert evalset.calibration[1].centre_error_median < 1e-5
    assert not evalset.has_frame(2) and any("robot 2: no snapshot" in n for n in notes)
    notes = calibrate_frames(EvalSet.from_dir(out / "data"), run, {1: [], 2: [0]}, echo=lambda _: None)
    assert any("the reference (robot 1) has no calibrated frame" in n for n in notes)

    # "alone" for an images-only robot: its calibrated frame and the split's box, no traceback
    torch_threads = torch.get_num_threads()
    try:
        res = train_alone(run, 2, spec.training, 3, with_ssim=spec.report.ssim)
    finally:
        torch.set_num_threads(torch_threads)
    assert isinstance(res, AloneScores) and math.isfinite(res.psnr)


def test_markdown_shows_the_calibration_and_a_failed_baseline(tmp_path):
    spec = spec_from(tmp_path)
    cal = {"matched": 40, "inliers": 39, "centre_error_median": 0.0123, "rotation_error_median_deg": 0.21, "scale": 3.1}
    final = {"psnr": 20.0, "psnr_others_only": 18.0, "rotation_error_deg": 0.5, "translation_error": 0.02}
    robot = {"final": final, "final_round": 1, "seconds_per_step_mean": 0.1, "seconds_wait_total": 1.0,
             "bytes_out_total": 1e6, "starts": 1, "rounds": {}}
    report = {
        "ok": True, "reason": "all robots finished", "seconds_run": 10.0, "mode": "local", "heldout_views": 4,
        "split": {"resolution": [24, 24], "robot_resolution": [48, 48], "mean_overlap": 0.2},
        "notes": ["images only: ..."], "faults": [], "links_bytes": {},
        "robots": {"1": {**robot, "calibration": cal}, "2": {**robot, "calibration": None}},
        "baseline": {"steps": 4, "centralised": {"psnr": 22.0, "ssim": None},
                     "alone": {"1": {"psnr": 15.0, "psnr_others_only": 12.0}, "2": {"error": "DataError: no SfM"}}},
        "summary": {"mean_psnr": 20.0, "mean_psnr_others_only": 18.0, "max_rotation_error_deg": 0.5,
                    "max_translation_error": 0.02, "gap_to_centralised_db": 2.0,
                    "gain_over_alone_others_only_db": {"1": 6.0}},
    }
    md = report_mod._markdown(report, spec, spec.ids)
    assert "## Evaluation frames (images only)" in md
    assert "| 1 | 40 | 39 | 0.0123 | 0.210 | 3.1 |" in md and "| 2 | n/a |" in md
    assert "robots' images at [48, 48]" in md and "images only" in md
    assert "robot 2 alone failed: DataError: no SfM" in md


@pytest.mark.skipif(not LEGO.is_dir(), reason=f"lego not found at {LEGO} (the repo's sibling shared/data)")
def test_lego_images_only_split(tmp_path):
    """The shipped scenario's split: 400 px robot images for SfM, 100 px held-out views."""
    spec = load_scenario(find_scenario("lego-2-images-only"))
    summary = prepare_split(spec, tmp_path)
    assert summary["resolution"] == [100, 100] and summary["robot_resolution"] == [400, 400]
    assert load_views(tmp_path / "eval").width == 100
    truth = read_truth(tmp_path)
    for rid in (1, 2):
        assert len(truth["robots"][str(rid)]["cameras_world"]) == summary["robots"][rid]["views"]
        assert not (tmp_path / f"robot{rid}/transforms.json").exists()
