"""Training end to end: RobotTrainer overfits the procedural scene; `dinerf-agent baseline` in a subprocess."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import pytest
import torch

from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box
from agent.data.views import Views
from agent.geometry import box_from_center, rotation_angle_deg
from agent.nerf.encoding import HashGridConfig
from agent.nerf.field import FieldConfig
from agent.nerf.occupancy import OccupancyConfig
from agent.nerf.sampler import MarchConfig
from agent.trainer import CameraRefineConfig, RobotTrainer, TrainConfig

ROOT = Path(__file__).resolve().parents[2]


def small_config(steps: int) -> TrainConfig:
    """A model sized for 32x32 images: ~15 s for 400 steps on one loaded core."""
    return TrainConfig(
        rays_per_step=1024,
        total_steps=steps,
        field=FieldConfig(grid=HashGridConfig(num_levels=8, log2_hashmap_size=14, base_resolution=8, max_resolution=128),
                          density_hidden=32, color_hidden=32, sh_degree=2),
        occupancy=OccupancyConfig(resolution=32, warmup_steps=64, update_every=8),
        march=MarchConfig(step_size=2 * math.sqrt(3) / 64),
    )


@pytest.mark.slow
def test_trainer_overfits_the_procedural_scene_past_25_db():
    views = load_views("procedural:views=24,width=32")  # RGBA, exact depth
    center, half, _ = estimate_scene_box(views)
    trainer = RobotTrainer(views, small_config(400), box_from_center(center, half))
    trainer.train(400)
    seen = views.subset([0, 7, 14, 21])  # training views
    scores = trainer.evaluate(seen, with_ssim=False)
    assert min(scores["psnr"]) > 25.0, scores  # ~28 dB when healthy; an untrained field gives ~11
    renders = [trainer.render(seen.c2w[i], seen.intrinsics[i], seen.width, seen.height) for i in range(len(seen))]
    opacity = torch.stack([r["opacity"] for r in renders])  # [4, H, W]
    depth = torch.stack([r["depth"] for r in renders])
    alpha = seen.images[..., 3]
    # random backgrounds taught it empty space: clear background, solid objects, the right depth
    assert float(opacity[alpha == 0].mean()) < 0.1 and float(opacity[alpha == 1].mean()) > 0.9
    assert float((depth - seen.depth)[alpha == 1].abs().median()) < 0.1  # scene units (objects span ~2)
    assert trainer.grid.occupied_fraction < 0.6  # the grid pruned empty space


def test_render_gradients_reach_the_relative_pose_through_the_rays():
    views = load_views("procedural:views=2,width=8")
    center, half, _ = estimate_scene_box(views)
    cfg = small_config(10)
    cfg.pose.mode = "sim3"
    trainer = RobotTrainer(views, cfg, box_from_center(center, half))
    trainer.train_step()  # one step: a random-colour loss through render_rays
    pose = trainer.pose
    for p in (pose.phi, pose.translation, pose.log_scale):
        assert p.grad is not None and float(p.grad.abs().sum()) > 0


def baseline_cli(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("dinerf-agent")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "cli.main"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "COLUMNS": "100"}
    return subprocess.run([*cmd, "baseline", *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.slow  # 5-10 s: a fresh interpreter imports torch and trains 20 steps
def test_baseline_command_writes_metrics_renders_and_checkpoint(tmp_path):
    out = tmp_path / "run"
    res = baseline_cli("--data", "procedural:views=16,width=16", "--steps", "20", "--out", str(out), "--threads", "1",
                       "--renders", "1", "--set", "occupancy.resolution=16", "--set", "field.grid.log2_hashmap_size=12",
                       "--set", "field.grid.num_levels=4", "--set", "field.grid.max_resolution=64")
    assert res.returncode == 0, res.stderr
    assert "held-out PSNR" in res.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == 20 and metrics["resolution"] == [16, 16]
    assert metrics["heldout_views"] == ["view_000", "view_008"] and metrics["train_views"] == 14
    assert len(metrics["psnr_per_view"]) == 2 and all(math.isfinite(p) for p in metrics["psnr_per_view"])
    assert 0 < metrics["seconds_per_step_median"] < 10 and -1 <= metrics["ssim"] <= 1
    png = cv2.imread(str(out / "renders" / "view_000.png"))
    assert png is not None and png.shape == (16, 32, 3)  # prediction | truth side by side
    from agent.checkpoint import CHECKPOINT, load_baseline

    trainer_state, cfg = load_baseline(out / CHECKPOINT)
    assert trainer_state["step"] == 20 and "table" in "".join(trainer_state["field"])
    assert cfg.total_steps == 20 and cfg.field.grid.num_levels == 4


def test_baseline_on_a_missing_folder_is_one_line_and_exit_code_2(tmp_path):
    res = baseline_cli("--data", str(tmp_path / "absent"), "--steps", "5", "--out", str(tmp_path / "o"))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "absent" in lines[0], res.stderr
    assert "Traceback" not in res.stderr + res.stdout
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_a_pose_started_from_an_estimate_learns_with_smaller_steps_and_remembers_it():
    views = load_views("procedural:views=2,width=8")
    center, half, _ = estimate_scene_box(views)
    cfg = small_config(100)
    cfg.pose.mode = "se3"
    box = box_from_center(center, half)
    identity = RobotTrainer(views, cfg, box)
    estimated = RobotTrainer(views, cfg, box, initial_pose=torch.eye(4))
    factor = cfg.pose.lr_factor_from_estimate
    assert 0 < factor < 1
    for step in (0, 50, 99):
        assert estimated._pose_lr_factor(step) == pytest.approx(factor * identity._pose_lr_factor(step))
    identity.pose.set_initial(torch.eye(4))  # what the daemon does after the coarse alignment
    assert identity._pose_lr_factor(50) == pytest.approx(estimated._pose_lr_factor(50))
    fresh = RobotTrainer(views, cfg, box)
    fresh.load_state_dict(estimated.state_dict())  # a restart keeps the smaller steps
    assert fresh.pose.from_estimate


def test_an_estimate_with_a_sigma_lets_the_pose_travel_only_a_few_sigma():
    """With the coarse estimate's rotation sigma, the whole schedule's rotation steps add up to
    pose.travel_sigmas x sigma: a precise estimate is barely moved, a loose one learns at full rate."""
    views = load_views("procedural:views=2,width=8")
    center, half, _ = estimate_scene_box(views)
    cfg = small_config(300)
    cfg.pose.mode = "sim3"
    cfg.pose.start_step = 100
    trainer = RobotTrainer(views, cfg, box_from_center(center, half))
    travels = []
    for sigma_deg in (0.02, 0.2):
        trainer.pose.set_initial(torch.eye(4), sigma_deg=sigma_deg)
        steps = sum(trainer._pose_lr_factor(s) * cfg.pose.lr_rotation for s in range(cfg.total_steps))
        travels.append(math.degrees(steps))
        assert travels[-1] == pytest.approx(cfg.pose.travel_sigmas * sigma_deg, rel=1e-6)
        assert trainer._pose_lr_factor(99) == 0.0  # still waits for the field
    assert trainer.pose_lr_scale() < 1.0
    for arrived in (100, 150, 200):  # placed late: the same travel over what is left of the run
        trainer.pose.set_initial(torch.eye(4), sigma_deg=0.2, step=arrived)
        steps = sum(trainer._pose_lr_factor(s) * cfg.pose.lr_rotation for s in range(arrived, cfg.total_steps))
        assert math.degrees(steps) == pytest.approx(cfg.pose.travel_sigmas * 0.2, rel=1e-6)
    trainer.pose.set_initial(torch.eye(4), sigma_deg=0.2, step=299)  # too late for that: full rate, no more
    assert trainer.pose_lr_scale() == 1.0
    trainer.pose.set_initial(torch.eye(4), sigma_deg=45.0)  # a loose estimate: full rate, no more
    assert trainer.pose_lr_scale() == 1.0
    fresh = RobotTrainer(views, cfg, box_from_center(center, half))
    fresh.load_state_dict(trainer.state_dict())  # a restart keeps the estimate's sigma
    assert fresh.pose.estimate_sigma_deg == 45.0 and fresh.pose_lr_scale() == 1.0
    trainer.pose.set_initial(torch.eye(4), sigma_deg=0.2, step=250)
    fresh.load_state_dict(trainer.state_dict())  # ... and the step it arrived at
    assert fresh.pose.estimate_step == 250 and fresh.pose_lr_scale() == pytest.approx(trainer.pose_lr_scale())


def test_fit_view_pose_undoes_a_misplaced_held_out_camera():
    """Test-time pose fitting (pose-free NeRF evaluation) moves a camera off by 1 deg back onto its image."""
    from agent.evaluation import fit_view_pose
    from agent.geometry import so3_exp
    from agent.metrics import psnr

    views = load_views("procedural:views=40,width=32")
    train = views.subset(list(range(1, 40)))
    held = views.subset([0])
    center, half, _ = estimate_scene_box(views)
    trainer = RobotTrainer(train, small_config(300), box_from_center(center, half))
    trainer.train(300)
    truth = held.c2w[0].float()
    turn = torch.eye(4)
    turn[:3, :3] = so3_exp(torch.tensor([0.0, math.radians(1.0), 0.0]))
    off = truth @ turn
    gt = held.rgb(1.0)[0]
    k = held.intrinsics[0]

    def score(c2w):
        return psnr(trainer.render(c2w, k, held.width, held.height, 1.0)["rgb"], gt)

    fitted = fit_view_pose(trainer, off, k, gt, steps=60)
    print(f"true pose {score(truth):.2f} dB, off by 1 deg {score(off):.2f}, fitted {score(fitted):.2f}")
    assert score(fitted) > score(off) + 1.0
    assert score(fitted) > score(truth) - 1.0


def test_own_views_psnr_scores_the_robots_views_through_its_refined_cameras():
    """The report's fit-of-own-views figure: one in k training views, seen through the cameras as
    refined; cameras that disagree with the field (here turned 2 deg after training) score lower."""
    views = load_views("procedural:views=24,width=32")
    center, half, _ = estimate_scene_box(views)
    cfg = small_config(300)
    cfg.cameras = CameraRefineConfig(enabled=True, start_step=10_000)  # on, but never moving during training
    trainer = RobotTrainer(views, cfg, box_from_center(center, half))
    trainer.train(300)
    own = trainer.own_views_psnr(every=5)
    assert len(own) == 5  # views 0, 5, 10, 15, 20
    direct = trainer.evaluate(views.subset([0, 5, 10, 15, 20]), with_ssim=False)["psnr"]
    assert own == pytest.approx(direct, abs=1e-3)
    with torch.no_grad():
        trainer.view_phi[:, 1] = math.radians(2.0)
    turned = trainer.own_views_psnr(every=5)
    print(f"own views {sum(own) / 5:.2f} dB, cameras turned 2 deg {sum(turned) / 5:.2f} dB")
    assert sum(turned) / 5 < sum(own) / 5 - 2.0


@pytest.mark.slow
def test_camera_refinement_undoes_misplaced_cameras_and_a_wrong_focal_length():
    """Training cameras each turned by ~1 deg and a focal length 4% long (what a robot's own SfM
    gets wrong): with refinement the field fits a held-out true view better, and the learnt focal
    scale goes the right way."""
    from agent.geometry import so3_exp

    views = load_views("procedural:views=40,width=32")
    held = views.subset([0, 20])
    train = views.subset([i for i in range(40) if i not in (0, 20)])
    g = torch.Generator().manual_seed(0)
    axes = torch.nn.functional.normalize(torch.randn(len(train), 3, generator=g), dim=-1)
    turns = torch.eye(4).repeat(len(train), 1, 1)
    turns[:, :3, :3] = so3_exp(axes * math.radians(1.0))
    wrong = Views(train.images, train.c2w @ turns, train.intrinsics * torch.tensor([1.04, 1.04, 1.0, 1.0]),
                  list(train.names), train.depth, train.meta)
    center, half, _ = estimate_scene_box(views)
    scores = {}
    for refine in (False, True):
        cfg = small_config(500)
        cfg.cameras = CameraRefineConfig(enabled=refine, lr_rotation=1e-3, lr_translation=1e-3, lr_focal=1e-3,
                                         start_step=100)
        trainer = RobotTrainer(wrong, cfg, box_from_center(center, half))
        trainer.train(500)
        scores[refine] = sum(trainer.evaluate(held, with_ssim=False)["psnr"]) / len(held)
        if refine:
            focal = math.exp(float(trainer.log_focal.detach()))
            turned = trainer.refined_views().c2w
    err_before = rotation_angle_deg(wrong.c2w[:, :3, :3], train.c2w[:, :3, :3]).mean()
    err_after = rotation_angle_deg(turned[:, :3, :3], train.c2w[:, :3, :3]).mean()
    print(f"held-out PSNR {scores[False]:.2f} dB without refinement, {scores[True]:.2f} with; focal x{focal:.4f} "
          f"(truth x{1 / 1.04:.4f}); camera rotation error {err_before:.3f} -> {err_after:.3f} deg")
    assert scores[True] > scores[False] + 0.5
    assert focal < 1.0  # shortened, towards the truth (1/1.04 = 0.962); it moves slowly: the field absorbs part of a zoom
    assert err_after < err_before


def test_a_checkpoint_from_before_camera_refinement_still_loads():
    """Runs saved before the camera groups existed (5 optimiser groups, no "cameras") resume and report."""
    views = load_views("procedural:views=8,width=16")
    center, half, _ = estimate_scene_box(views)
    old = RobotTrainer(views, small_config(4), box_from_center(center, half))
    old.train(2)
    state = old.state_dict()
    del state["cameras"]
    names = [g["name"] for g in old.optimizer.param_groups]
    keep = names.index("view_rotation")  # the old optimiser stopped before the camera groups
    state["optimizer"]["param_groups"] = state["optimizer"]["param_groups"][:keep]
    fresh = RobotTrainer(views, small_config(4), box_from_center(center, half))
    fresh.load_state_dict(state)
    assert fresh.step == 2 and [g["name"] for g in fresh.optimizer.param_groups] == names
    assert all(torch.equal(a, b) for a, b in zip(fresh.field.parameters(), old.field.parameters()))
    fresh.train(1)  # and it trains on


def test_the_depth_term_does_not_depend_on_the_scale_of_the_robots_frame():
    """An SfM frame has an arbitrary scale, and so has its depth prior: the same robot in a frame
    10x larger (cameras and depths x10, its pose scale 1/10) must see the same depth loss, or the
    weight would mean something else on every robot."""
    from dataclasses import replace

    from agent.trainer import DepthConfig

    views = load_views("procedural:views=8,width=16")  # exact depth
    center, half, _ = estimate_scene_box(views)
    box = box_from_center(center, half)
    cfg = replace(small_config(10), depth=DepthConfig(weight=0.1))
    big_c2w = views.c2w.clone()
    big_c2w[:, :3, 3] *= 10.0
    big = Views(views.images, big_c2w, views.intrinsics, list(views.names), views.depth * 10.0)
    shrink = torch.diag(torch.tensor([0.1, 0.1, 0.1, 1.0]))  # big local frame -> the shared frame
    losses = [RobotTrainer(v, cfg, box, initial_pose=pose).train_step()["depth_loss"]
              for v, pose in ((views, torch.eye(4)), (big, shrink))]
    assert losses[0] > 0 and losses[1] == pytest.approx(losses[0], rel=1e-4), losses


def test_a_sample_budget_shrinks_the_batch_while_rays_hold_many_samples():
    """``target_samples_per_step``: rays a step = budget / samples a ray (running mean), between
    ``min_rays_per_step`` and ``rays_per_step``."""
    views = load_views("procedural:views=2,width=16")
    center, half, _ = estimate_scene_box(views)
    cfg = small_config(10)
    cfg.target_samples_per_step, cfg.min_rays_per_step = 8192, 64
    trainer = RobotTrainer(views, cfg, box_from_center(center, half))
    asked = []
    sample_pixels = trainer._sample_pixels
    trainer._sample_pixels = lambda n: (asked.append(n), sample_pixels(n))[1]
    for samples_a_ray, rays in ((100.0, 81), (4.0, 1024), (1000.0, 64)):
        trainer.samples_per_ray = samples_a_ray
        trainer.train_step()
        assert asked[-1] == rays
