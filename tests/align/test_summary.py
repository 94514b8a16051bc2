"""Keyframe summaries from rendered views, and the coarse estimate between two robots end to end."""

import dataclasses

import numpy as np
import pytest
import torch

from agent import geometry as G
from agent.align import AlignConfig, estimate_relative, summarise
from agent.align.keypoints import project_keypoints as _project
from tests.align.scene import TexturedScene, render_views, ring_cameras


@pytest.fixture(scope="module")
def scene():
    return TexturedScene(0)


def _robot(scene, azimuths, t_local_from_world=None):
    views = render_views(scene, ring_cameras(azimuths), 200, 150, 190.0)
    if t_local_from_world is not None:  # the robot's own frame: cameras and depth move with it
        t = torch.as_tensor(t_local_from_world, dtype=torch.float64)
        views.c2w = G.transform_c2w(t, views.c2w.double()).float()
        views.depth = views.depth * float(G.sim3_decompose(t)[0])
    return views


def _depth_error(views, summary):
    """Relative z-depth error of each summary point against the rendered depth in its keyframe."""
    errs = []
    for slot, name in enumerate(summary.meta["keyframes"]):
        i = views.names.index(name)
        pts = summary.points[summary.keyframe_index == slot].astype(np.float64)
        uv, z = _project(views.c2w[i].double().numpy(), views.intrinsics[i].double().numpy(), pts)
        px = np.clip(np.floor(uv + 0.5).astype(int), 0, [views.width - 1, views.height - 1])
        true = views.depth[i].numpy()[px[:, 1], px[:, 0]]
        ok = true > 0
        errs.append(np.abs(z[ok] - true[ok]) / true[ok])
    return np.concatenate(errs)


def test_summary_is_compact_and_its_points_lie_on_the_surface(scene):
    views = _robot(scene, np.arange(0, 160, 8))
    cfg = AlignConfig(num_keyframes=6)
    summ = summarise(views, "triangulate", cfg)
    image_bytes = views.images.numel()  # as 8-bit files: 1 byte per channel value
    assert 200 <= len(summ) and summ.nbytes <= cfg.max_bytes and summ.nbytes < image_bytes / 4
    assert summ.descriptors.dtype == np.uint8 and summ.points.dtype == np.float32
    assert set(np.unique(summ.keyframe_index)) == set(range(6))  # every keyframe contributes
    err = _depth_error(views, summ)
    assert np.median(err) < 0.01 and (err < 0.05).mean() > 0.9
    # A tight byte budget is honoured, spread over the keyframes.
    small = summarise(views, "triangulate", AlignConfig(num_keyframes=6, max_bytes=20_000))
    assert small.nbytes <= 20_000 and len(np.unique(small.keyframe_index)) == 6
    # Depth source: the rendered (metric) depth places the points exactly, on more features.
    dsum = summarise(views, "auto", cfg)
    assert dsum.meta["points_source"] == "depth" and dsum.meta["depth"] > 0
    assert np.median(_depth_error(views, dsum)) < 0.005
    # Deterministic.
    again = summarise(views, "triangulate", cfg)
    assert np.array_equal(again.points, summ.points) and np.array_equal(again.descriptors, summ.descriptors)


@pytest.mark.parametrize("with_scale", [True, False])
def test_two_robots_in_their_own_frames_are_aligned(scene, with_scale):
    g = torch.Generator().manual_seed(7)
    t_b = torch.eye(4, dtype=torch.float64)  # b's local frame from the world: 150 deg turn, far away
    scale = 0.3 if with_scale else 1.0
    t_b[:3, :3] = scale * G.random_rotation(g, 180.0)
    t_b[:3, 3] = torch.tensor([6.0, -9.0, 4.0], dtype=torch.float64)
    a = _robot(scene, np.arange(0, 150, 8))  # the reference: world frame
    b = _robot(scene, np.arange(100, 250, 8), t_b)  # 50 deg of shared arc, no identical images
    cfg = AlignConfig(num_keyframes=8, with_scale=with_scale)
    res = estimate_relative(summarise(a, "triangulate", cfg), summarise(b, "triangulate", cfg), cfg)
    assert res.success, res.reason
    err = G.pose_error(torch.from_numpy(res.T_a_from_b), G.sim3_inverse(t_b))
    assert err["rotation_deg"] < 1.0 and err["scale_rel"] < 0.01 and err["translation"] < 0.2, err


def test_robots_of_different_scenes_do_not_align(scene):
    a = _robot(scene, np.arange(0, 150, 8))
    other = _robot(TexturedScene(1), np.arange(0, 150, 8))  # same cameras, different world
    cfg = AlignConfig(num_keyframes=8)
    res = estimate_relative(summarise(a, "triangulate", cfg), summarise(other, "triangulate", cfg), cfg)
    assert not res.success and res.T_a_from_b is None, res


def test_reprojection_refinement_tightens_the_3d_fit(scene):
    """Keypoints and keyframe cameras travel with the summary; measuring the matches in pixels
    beats the 3-D/3-D fit, whose points are uncertain mostly along their viewing rays."""
    g = torch.Generator().manual_seed(11)
    t_b = torch.eye(4, dtype=torch.float64)
    t_b[:3, :3] = 2.0 * G.random_rotation(g, 180.0)
    t_b[:3, 3] = torch.tensor([-7.0, 3.0, 5.0], dtype=torch.float64)
    a = _robot(scene, np.arange(0, 150, 8))
    b = _robot(scene, np.arange(100, 250, 8), t_b)
    cfg = AlignConfig(num_keyframes=8)
    sa, sb = summarise(a, "triangulate", cfg), summarise(b, "triangulate", cfg)
    rng = np.random.default_rng(0)
    for s in (sa, sb):  # each keypoint is where its point projects in its keyframe
        # ... and then 3% depth noise along the viewing rays, the error of a narrow-baseline
        # triangulation (lego at 100 px), which the 3-D fit cannot tell from lateral error.
        centres = s.keyframe_cameras[s.keyframe_index][:, [3, 7, 11]].astype(np.float64)
        clean = s.points.astype(np.float64)
        ray = clean - centres
        cams = s.keyframe_cameras[s.keyframe_index].astype(np.float64)
        c2w = np.concatenate([cams[:, :12].reshape(-1, 3, 4), np.tile([[[0, 0, 0, 1.0]]], (len(s), 1, 1))], 1)
        uv = np.stack([_project(c2w[i], cams[i, 12:], s.points[i:i + 1].astype(np.float64))[0][0] for i in range(len(s))])
        assert np.median(np.linalg.norm(uv - s.keypoints, axis=1)) < 0.5
        s.points[:] = (centres + ray * (1 + 0.03 * rng.standard_normal((len(s), 1)))).astype(np.float32)
    truth = G.sim3_inverse(t_b)  # T_a_from_b: a's frame is the world

    def camera_error(res):
        est = G.transform_points(torch.from_numpy(res.T_a_from_b), b.c2w[:, :3, 3].double())
        return float((est - G.transform_points(truth, b.c2w[:, :3, 3].double())).norm(dim=1).mean())

    fit_3d = estimate_relative(sa, sb, dataclasses.replace(cfg, reproj_refine=False))
    refined = estimate_relative(sa, sb, cfg)
    assert fit_3d.success and refined.success and "refined on reprojection" in refined.reason, refined.reason
    err_3d = G.pose_error(torch.from_numpy(fit_3d.T_a_from_b), truth)
    err = G.pose_error(torch.from_numpy(refined.T_a_from_b), truth)
    print(f"3-D fit {err_3d}, cameras {camera_error(fit_3d):.4f}; refined {err}, cameras {camera_error(refined):.4f}")
    assert camera_error(refined) < 0.7 * camera_error(fit_3d)
    assert err["rotation_deg"] < err_3d["rotation_deg"] and err["rotation_deg"] < 0.2
    # Without cameras on one side (an older peer), the 3-D fit is what comes back.
    bare = dataclasses.replace(sb, keypoints=None, keyframe_cameras=None)
    assert np.array_equal(estimate_relative(sa, bare, cfg).T_a_from_b, fit_3d.T_a_from_b)


def test_the_rotation_sigma_grows_with_keypoint_noise_and_bounds_the_error(scene):
    """The estimate states its own rotation 1-sigma (the joint optimisation's pose learns at a rate
    set by it): noisier keypoints give a larger sigma, and the error stays within a few sigma."""
    g = torch.Generator().manual_seed(5)
    t_b = torch.eye(4, dtype=torch.float64)
    t_b[:3, :3] = 0.5 * G.random_rotation(g, 180.0)
    t_b[:3, 3] = torch.tensor([4.0, 8.0, -6.0], dtype=torch.float64)
    a = _robot(scene, np.arange(0, 150, 8))
    b = _robot(scene, np.arange(100, 250, 8), t_b)
    cfg = AlignConfig(num_keyframes=8)
    clean_a, clean_b = summarise(a, "triangulate", cfg), summarise(b, "triangulate", cfg)
    truth = G.sim3_inverse(t_b)
    sigmas, errors = [], []
    for noise_px in (0.2, 2.0):
        rng = np.random.default_rng(1)
        sa, sb = (dataclasses.replace(s, keypoints=(s.keypoints + noise_px * rng.standard_normal(s.keypoints.shape)
                                                   ).astype(np.float32)) for s in (clean_a, clean_b))
        res = estimate_relative(sa, sb, cfg)
        assert res.success and "refined on reprojection" in res.reason, res.reason
        sigmas.append(res.rotation_sigma_deg)
        errors.append(G.pose_error(torch.from_numpy(res.T_a_from_b), truth)["rotation_deg"])
    print(f"sigma {sigmas}, error {errors} deg")
    assert all(np.isfinite(sigmas)) and 0 < sigmas[0] < sigmas[1] / 3
    assert all(e <= 3 * s for e, s in zip(errors, sigmas))
    # Without the refinement there is no sigma, and the pose learns at the configured fixed factor.
    assert np.isnan(estimate_relative(clean_a, clean_b, dataclasses.replace(cfg, reproj_refine=False)).rotation_sigma_deg)
