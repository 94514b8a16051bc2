"""Images-only splits and their evaluation: truth.json's world cameras, the null box, and the
Sim(3) calibration of a robot's SfM frame on its cameras."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import pytest
import torch

from agent.data.folder import read_scene, read_truth
from agent.data.procedural import ProceduralConfig, procedural_views
from agent.data.sfm import read_camera_file
from agent.data.split import SplitConfig, split_views, write_split
from agent.data.views import DataError, Views
from agent.evaluation import EvalSet, calibrate_frame, evaluate_robot
from agent.geometry import pose_error, random_rotation, sim3_inverse, transform_c2w


@pytest.fixture(scope="module")
def views() -> Views:
    return procedural_views(ProceduralConfig(num_views=40, width=16, height=16, seed=0))


def _sim3(seed: int, scale: float) -> torch.Tensor:
    """A Sim(3) [4, 4] float64 with a random rotation and translation, given scale."""
    gen = torch.Generator().manual_seed(seed)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = scale * random_rotation(gen)
    out[:3, 3] = torch.randn(3, generator=gen, dtype=torch.float64) * 3
    return out


def _sfm_views(local: Views, t_sfm_from_world: torch.Tensor, cameras_world: torch.Tensor) -> Views:
    """What a robot's SfM would give: its views with the true cameras in an arbitrary Sim(3) frame."""
    c2w = transform_c2w(t_sfm_from_world, cameras_world).float()
    return Views(local.images, c2w, local.intrinsics, list(local.names))


def test_calibration_recovers_a_synthetic_sim3(views):
    world = views.c2w.double()
    t_true = _sim3(1, 0.37)  # world <- local
    local = transform_c2w(sim3_inverse(t_true), world)
    truth = dict(zip(views.names, world))
    cal = calibrate_frame(views.names, local, truth)
    assert torch.allclose(cal.T_world_from_local, t_true, atol=1e-9)
    assert cal.matched == cal.inliers == len(views)
    assert cal.centre_error_median < 1e-9 and cal.rotation_error_median_deg < 1e-5
    assert cal.summary()["scale"] == pytest.approx(0.37)

    # one mis-registered view (centre far off) is dropped and does not tilt the frame
    bad = local.clone()
    bad[3, :3, 3] += 5.0
    cal = calibrate_frame(views.names, bad, truth)
    assert cal.inliers == len(views) - 1
    assert torch.allclose(cal.T_world_from_local, t_true, atol=1e-9)

    # SfM noise: the residual is reported, the frame still close
    noisy = local.clone()
    noisy[:, :3, 3] += 0.01 * torch.randn(len(views), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    cal = calibrate_frame(views.names, noisy, truth)
    assert 1e-4 < cal.centre_error_median < 0.02
    assert pose_error(cal.T_world_from_local, t_true)["rotation_deg"] < 0.5

    # names are what matches cameras: views the truth does not know are ignored, too few is an error
    cal = calibrate_frame(views.names[:5] + ["unknown"], torch.cat([local[:5], local[:1]]), truth)
    assert cal.matched == 5
    with pytest.raises(DataError, match=">= 3"):
        calibrate_frame(["a", "b"], local[:2], truth)


def test_images_only_split_writes_world_cameras_and_no_box(views, tmp_path):
    r = split_views(views, SplitConfig(robots=2, overlap=0.2, test_every=5, frame="random", images_only=True, seed=3))
    write_split(r, tmp_path)
    assert not (tmp_path / "robot1/transforms.json").exists() and not (tmp_path / "robot2/transforms.json").exists()
    scene = json.loads((tmp_path / "scene.json").read_text())
    assert scene["box_from_shared"] is None and scene["reference_id"] == 1 and "SfM" in scene["description"]
    assert read_scene(tmp_path).box_from_shared is None
    truth = read_truth(tmp_path)
    assert truth["images_only"] is True
    for rid, rob in r.robots.items():
        entry = truth["robots"][str(rid)]
        assert "T_world_from_local" not in entry, "a split frame the robot never sees would mislead"
        cams = entry["cameras_world"]
        assert list(cams) == rob.views.names
        expect = views.c2w[rob.indices].double()
        got = torch.tensor([cams[n] for n in rob.views.names], dtype=torch.float64)
        assert torch.allclose(got, expect, atol=1e-5), "the true world cameras of the robot's own views"
        assert read_camera_file(tmp_path / f"robot{rid}") is None, "an uncalibrated robot guesses its focal length"

    ev = EvalSet.from_dir(tmp_path)
    assert ev.needs_calibration and not ev.has_frame(1) and ev.box_from_world is not None
    with pytest.raises(DataError, match="calibrate it first"):
        ev.shared_cameras()


def test_a_split_with_calibrated_cameras_gives_each_robot_its_focal_length_and_no_pose(views, tmp_path):
    cfg = SplitConfig(robots=2, overlap=0.2, test_every=5, images_only=True, calibrated_cameras=True)
    write_split(split_views(views, cfg), tmp_path)
    for rid in (1, 2):
        cam = read_camera_file(tmp_path / f"robot{rid}")
        assert cam == {"focal_px": pytest.approx(float(views.intrinsics[0, 0])), "width": views.width, "fixed": True}
        assert not (tmp_path / f"robot{rid}/transforms.json").exists()
    with pytest.raises(DataError, match="calibrated_cameras is for images_only"):
        SplitConfig(robots=2, calibrated_cameras=True)


def test_evaluation_in_calibrated_sfm_frames(views):
    """Two robots in SfM frames of different scales: after calibration the shared frame is robot 1's
    SfM frame, and the pose error is in scene units whatever that frame's scale."""
    r = split_views(views, SplitConfig(robots=2, overlap=0.2, test_every=5, images_only=True))
    ev = EvalSet.from_split(r)
    assert ev.needs_calibration and not ev.T_world_from_local
    sfm = {1: _sim3(11, 0.25), 2: _sim3(12, 3.0)}  # sfm <- world per robot
    for rid, rob in r.robots.items():
        ev.calibrate(rid, _sfm_views(rob.views, sfm[rid], rob.cameras_world))
    for rid in (1, 2):
        assert torch.allclose(ev.T_world_from_local[rid], sim3_inverse(sfm[rid]), atol=1e-8)
    truth_2 = sfm[1] @ sim3_inverse(sfm[2])  # robot 2's SfM -> robot 1's SfM
    assert torch.allclose(ev.T_shared_from_local(2), truth_2, atol=1e-8)
    assert torch.allclose(ev.shared_cameras().double(), transform_c2w(sfm[1], r.eval_views.c2w.double()), atol=1e-4)
    box = ev.box_from_shared @ sfm[1]  # back to the world: the split's box
    assert torch.allclose(box, r.box_from_world, atol=1e-6)  # float32 SfM cameras

    # an estimate 0.1 scene units off in translation reads 0.1, not 0.1 x (robot 1's SfM scale)
    off = torch.eye(4, dtype=torch.float64)
    off[:3, 3] = torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64)  # world units, applied in the world
    estimate = sfm[1] @ off @ ev.T_world_from_local[2]
    trainer = SimpleNamespace(
        evaluate=lambda v, frame, with_ssim, appearance: {"psnr": [20.0] * len(v), "ssim": [0.5] * len(v)},
        pose=SimpleNamespace(matrix=lambda: estimate.float()), appearance_for=lambda c2w: None,
    )
    err = evaluate_robot(trainer, ev, 2).pose
    assert err["translation"] == pytest.approx(0.1, rel=1e-3)
    assert err["rotation_deg"] < 1e-3 and err["scale_rel"] < 1e-5


def test_known_frames_are_unchanged_by_the_world_unit_pose_error(views):
    """With a split's own frames (scale 1), the pose error is the shared-frame error as before."""
    r = split_views(views, SplitConfig(robots=2, frame="offset"))
    ev = EvalSet.from_split(r)
    assert not ev.needs_calibration
    truth = ev.T_shared_from_local(2)
    estimate = truth.clone()
    estimate[:3, 3] += torch.tensor([0.0, 0.2, 0.0], dtype=torch.float64)
    trainer = SimpleNamespace(evaluate=lambda v, frame, with_ssim, appearance: {"psnr": [1.0] * len(v),
                                                                               "ssim": [1.0] * len(v)},
                              pose=SimpleNamespace(matrix=lambda: estimate.float()), appearance_for=lambda c2w: None)
    err = evaluate_robot(trainer, ev, 2).pose
    assert err == pytest.approx(pose_error(estimate, truth), abs=1e-5)


def test_held_out_views_are_seen_through_the_camera_that_built_the_frame(views):
    """An SfM focal length 2% short: the held-out views get the reference's (the swarm's field is
    in its frame), a robot trained alone its own; known frames keep the truth's."""
    r = split_views(views, SplitConfig(robots=2, overlap=0.2, test_every=5, images_only=True))
    ev = EvalSet.from_split(r)
    truth_k = ev.views.intrinsics.clone()
    assert torch.equal(ev.shared_intrinsics(), truth_k)  # nothing calibrated yet
    for rid, short in ((1, 0.98), (2, 0.95)):
        rob = r.robots[rid]
        sfm = _sfm_views(rob.views, _sim3(10 + rid, 1.0), rob.cameras_world)
        half = Views(sfm.images[:, ::2, ::2], sfm.c2w, sfm.intrinsics * torch.tensor([short / 2, short / 2, 0.5, 0.5]),
                     sfm.names)  # its SfM at half the evaluation's width
        ev.calibrate(rid, half)
    k = ev.shared_intrinsics()
    assert torch.allclose(k[:, :2], 0.98 * truth_k[:, :2]) and torch.equal(k[:, 2:], truth_k[:, 2:])
    assert torch.allclose(ev.shared_intrinsics(camera_of=2)[:, :2], 0.95 * truth_k[:, :2])
    seen = []
    trainer = SimpleNamespace(evaluate=lambda v, frame, with_ssim, appearance: seen.append(v.intrinsics) or
                              {"psnr": [1.0] * len(v), "ssim": [1.0] * len(v)},
                              pose=SimpleNamespace(matrix=lambda: ev.T_shared_from_local(2).float()),
                              appearance_for=lambda c2w: None)
    out = evaluate_robot(trainer, ev, 2, compare_true_intrinsics=True)
    assert torch.equal(seen[0], k) and torch.equal(seen[1], truth_k) and out.psnr_true_intrinsics is not None
    known = EvalSet.from_split(split_views(views, SplitConfig(robots=2, frame="offset")))
    assert torch.equal(known.shared_intrinsics(), known.views.intrinsics)


def test_a_summary_without_ssim_has_none_instead_of_failing():
    from agent.evaluation import RobotEval

    ev = RobotEval(robot_id=1, psnr=[20.0, 22.0], ssim=[], others_only=[1], psnr_true_intrinsics=[18.0, 18.0])
    s = ev.summary()
    assert s["psnr"] == 21.0 and s["psnr_others_only"] == 22.0 and s["psnr_true_intrinsics"] == 18.0
    assert math.isnan(s["ssim"]) and math.isnan(s["ssim_others_only"])
