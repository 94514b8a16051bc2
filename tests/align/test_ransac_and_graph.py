"""Pairwise estimate and graph composition on synthetic summaries (no images, milliseconds)."""

import math

import numpy as np
import pytest
import torch

from agent import geometry as G
from agent.align import (AlignConfig, AlignmentResult, Summary, compose_along_graph, estimate_relative,
                         ransac_sim3)


def _sim3(seed: int, with_scale: bool = True) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    rot = G.random_rotation(g, 180.0)
    out = torch.eye(4, dtype=torch.float64)
    scale = float(torch.exp(torch.randn((), generator=g, dtype=torch.float64))) if with_scale else 1.0
    out[:3, :3] = scale * rot
    out[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64) * 5
    return out.numpy()


def _apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ t[:3, :3].T + t[:3, 3]


def _surface_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on the faces of a unit cube: 2-D manifolds like real scene points."""
    p = rng.uniform(-1, 1, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = rng.choice([-1.0, 1.0], n)
    return p


def _descriptors(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.random((n, 128)) ** 3  # sparse-ish positive vectors, like SIFT histograms
    d = np.sqrt(d / d.sum(1, keepdims=True))
    return np.clip(np.rint(d * 512), 0, 255).astype(np.uint8)


def _summary(desc: np.ndarray, pts: np.ndarray) -> Summary:
    return Summary(desc, pts.astype(np.float32), np.zeros(len(pts), np.int32))


@pytest.mark.parametrize("with_scale", [True, False])
def test_ransac_recovers_a_known_transform_with_half_outliers(with_scale):
    rng = np.random.default_rng(0)
    t_true = _sim3(1, with_scale)
    src = _surface_points(rng, 200)
    dst = _apply(t_true, src) + rng.normal(0, 0.002, (200, 3))
    out = rng.permutation(200)[:100]  # 50 % outliers: random points of the destination scene
    dst[out] = _apply(t_true, _surface_points(rng, 100))
    scale = np.cbrt(abs(np.linalg.det(t_true[:3, :3])))
    cfg = AlignConfig(with_scale=with_scale)
    est, mask = ransac_sim3(src, dst, threshold=0.03 * scale, cfg=cfg)
    err = G.pose_error(torch.from_numpy(est), torch.from_numpy(t_true))
    assert err["rotation_deg"] < 0.3 and err["scale_rel"] < 3e-3
    assert err["translation"] < 0.02 * scale
    inlier_truth = np.ones(200, bool)
    inlier_truth[out] = False
    # Outliers that happen to land near their true position are legitimately inliers.
    assert mask[inlier_truth].mean() > 0.97 and (mask & ~inlier_truth).sum() < 10
    # Deterministic for the seed.
    est2, mask2 = ransac_sim3(src, dst, threshold=0.03 * scale, cfg=cfg)
    assert np.array_equal(est, est2) and np.array_equal(mask, mask2)


def test_estimate_relative_on_overlapping_summaries():
    rng = np.random.default_rng(1)
    t_a_from_b = _sim3(2)
    shared = _surface_points(rng, 150)  # seen by both robots
    desc_shared = _descriptors(rng, 150)
    pts_a = np.concatenate([shared + rng.normal(0, 0.003, shared.shape), _surface_points(rng, 300) + [3, 0, 0]])
    desc_a = np.concatenate([desc_shared, _descriptors(rng, 300)])
    b_local = np.concatenate([shared + rng.normal(0, 0.003, shared.shape), _surface_points(rng, 300) - [3, 0, 0]])
    pts_b = _apply(np.linalg.inv(t_a_from_b), b_local)  # b's points in b's own frame
    desc_b = np.concatenate([desc_shared, _descriptors(rng, 300)])
    perm = rng.permutation(450)
    res = estimate_relative(_summary(desc_a, pts_a), _summary(desc_b[perm], pts_b[perm]))
    assert res.success, res.reason
    assert res.inliers >= 100 and res.matches >= res.inliers
    err = G.pose_error(torch.from_numpy(res.T_a_from_b), torch.from_numpy(t_a_from_b))
    assert err["rotation_deg"] < 0.5 and err["scale_rel"] < 0.01 and err["translation"] < 0.05
    se3 = estimate_relative(_summary(desc_a, pts_a), _summary(desc_b[perm], pts_b[perm]), AlignConfig(with_scale=False))
    assert not se3.success or abs(se3.scale - 1) < 1e-9  # SE(3) never invents a scale


def test_no_overlap_fails_with_a_reason_instead_of_a_pose():
    rng = np.random.default_rng(3)
    # Independent scenes, independent descriptors: whatever matches survive are chance.
    a = _summary(_descriptors(rng, 800), _surface_points(rng, 800))
    b = _summary(_descriptors(rng, 800), _surface_points(rng, 800) * 2 + 5)
    res = estimate_relative(a, b)
    assert not res.success and res.T_a_from_b is None and res.reason
    # Even if descriptor matching is fooled (identical descriptors, unrelated geometry), the
    # geometric check rejects: b's points are a random shuffle of a's, so no rigid motion fits.
    desc = _descriptors(rng, 400)
    pts = _surface_points(rng, 400)
    fooled = estimate_relative(_summary(desc, pts), _summary(desc, pts[rng.permutation(400)]))
    assert fooled.matches > 300
    assert not fooled.success and fooled.T_a_from_b is None, fooled.reason
    # And an empty summary (a robot that saw nothing usable) is a clean failure too.
    empty = Summary(np.zeros((0, 128), np.uint8), np.zeros((0, 3), np.float32), np.zeros(0, np.int32))
    assert not estimate_relative(a, empty).success


def test_summary_payload_roundtrip_and_validation():
    rng = np.random.default_rng(4)
    s = _summary(_descriptors(rng, 10), _surface_points(rng, 10))
    back = Summary.from_arrays(s.to_arrays())
    assert np.array_equal(back.descriptors, s.descriptors) and np.array_equal(back.points, s.points)
    assert s.nbytes == 10 * (128 + 12 + 4)
    bad = dict(s.to_arrays(), points=np.full((10, 3), np.nan, np.float32))
    with pytest.raises(ValueError):
        Summary.from_arrays(bad)
    with pytest.raises(ValueError):
        Summary.from_arrays(dict(s.to_arrays(), version=99))
    with pytest.raises(ValueError):
        Summary.from_arrays(dict(s.to_arrays(), keyframe_index=np.zeros(9, np.int32)))


def test_compose_along_a_line_graph_and_unreachable_robots():
    # Truth: T_ref(0)_from_i for robots 0..3 on a line 0 - 1 - 2 - 3; robot 4 has no edge that works.
    truth = {0: np.eye(4), 1: _sim3(10), 2: _sim3(11), 3: _sim3(12)}

    def rel(a, b):  # T_a_from_b = T_0_from_a^-1 T_0_from_b
        return np.linalg.inv(truth[a]) @ truth[b]

    estimates = {
        (0, 1): rel(0, 1),
        (2, 1): AlignmentResult(rel(2, 1), 50, 80, 0.01, True, "ok"),  # given in the other direction
        (2, 3): rel(2, 3),
        (3, 4): AlignmentResult(None, 3, 20, float("nan"), False, "no overlap"),
    }
    out = compose_along_graph(0, estimates)
    assert set(out) == {0, 1, 2, 3}
    for k, t in truth.items():
        assert np.allclose(out[k], t, atol=1e-8), k
    # A non-reference root works the same way (the reference may change at run time).
    out1 = compose_along_graph(1, estimates)
    assert np.allclose(out1[3], np.linalg.inv(truth[1]) @ truth[3], atol=1e-8)


def test_compose_prefers_the_most_trusted_path():
    truth = {0: np.eye(4), 1: _sim3(20), 2: _sim3(21)}
    wrong = _sim3(22)

    def rel(a, b):
        return np.linalg.inv(truth[a]) @ truth[b]

    estimates = {
        (0, 2): AlignmentResult(wrong, 13, 100, 0.05, True, "weak"),  # a weak (and wrong) direct edge
        (0, 1): AlignmentResult(rel(0, 1), 200, 250, 0.01, True, "strong"),
        (1, 2): AlignmentResult(rel(1, 2), 150, 200, 0.01, True, "strong"),
    }
    out = compose_along_graph(0, estimates)
    assert np.allclose(out[2], truth[2], atol=1e-8)
    assert not math.isclose(float(np.abs(out[2] - wrong).max()), 0.0)


def test_initial_pose_falls_back_to_identity_and_says_so():
    from agent.align import initial_pose

    rng = np.random.default_rng(5)
    ref = _summary(_descriptors(rng, 300), _surface_points(rng, 300))
    t_ref_from_own = _sim3(30)
    own = _summary(ref.descriptors.copy(), _apply(np.linalg.inv(t_ref_from_own), ref.points.astype(np.float64)))
    t, res = initial_pose(own, ref)
    assert res.success and np.allclose(t, t_ref_from_own, atol=1e-3)
    stranger = _summary(_descriptors(rng, 300), _surface_points(rng, 300))
    t, res = initial_pose(stranger, ref)
    assert not res.success and np.array_equal(t, np.eye(4)) and res.reason
