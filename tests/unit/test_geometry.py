import math

import pytest
import torch

from agent import geometry as G


def _gen(seed=0):
    return torch.Generator().manual_seed(seed)


def test_exp_is_a_rotation_and_log_inverts_it_over_the_whole_range():
    g = _gen()
    for angle in [0.0, 1e-7, 1e-3, 0.5, 1.0, 3.0, math.pi - 1e-4, math.pi]:
        axis = torch.randn(3, generator=g, dtype=torch.float64)
        phi = axis / axis.norm() * angle
        rot = G.so3_exp(phi)
        assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
        assert torch.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
        back = G.so3_log(rot)
        if angle < math.pi - 1e-3:
            assert torch.allclose(back, phi, atol=1e-9), angle
        else:  # at pi, axis and -axis are the same rotation
            assert torch.allclose(G.so3_exp(back), rot, atol=1e-9)


def test_exp_matches_matrix_exponential_of_skew():
    phi = torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)
    assert torch.allclose(G.so3_exp(phi), torch.linalg.matrix_exp(G.skew(phi)), atol=1e-12)


def test_exp_gradient_is_finite_at_zero_and_equals_skew_generators():
    phi = torch.zeros(3, requires_grad=True)
    rot = G.so3_exp(phi)
    # d R / d phi_x at 0 is skew(e_x): check one entry through autograd.
    (g,) = torch.autograd.grad(rot[2, 1], phi)
    assert torch.isfinite(g).all()
    assert torch.allclose(g, torch.tensor([1.0, 0.0, 0.0]))


def test_sim3_params_roundtrip_inverse_and_compose():
    g = _gen(1)
    for _ in range(20):
        log_s = torch.randn((), generator=g, dtype=torch.float64) * 0.5
        phi = torch.randn(3, generator=g, dtype=torch.float64)
        t = torch.randn(3, generator=g, dtype=torch.float64) * 3
        T = G.sim3_from_params(log_s, phi, t)
        ls2, phi2, t2 = G.sim3_to_params(T)
        assert torch.allclose(G.sim3_from_params(ls2, phi2, t2), T, atol=1e-10)
        assert torch.allclose(G.sim3_compose(T, G.sim3_inverse(T)), torch.eye(4, dtype=torch.float64), atol=1e-10)
        x = torch.randn(5, 3, generator=g, dtype=torch.float64)
        y = G.transform_points(T, x)
        assert torch.allclose(G.transform_points(G.sim3_inverse(T), y), x, atol=1e-10)


def test_transform_c2w_keeps_rotation_orthonormal_and_moves_the_centre_like_a_point():
    g = _gen(2)
    T = G.sim3_from_params(torch.tensor(0.7, dtype=torch.float64), torch.randn(3, generator=g, dtype=torch.float64),
                           torch.randn(3, generator=g, dtype=torch.float64))
    c2w = G.look_at(torch.tensor([3.0, 1.0, 2.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    out = G.transform_c2w(T, c2w)
    r = out[:3, :3]
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-10)
    assert torch.allclose(out[:3, 3], G.transform_points(T, c2w[:3, 3][None])[0], atol=1e-10)
    # A point seen at depth z along the optical axis moves like a point too (scale applies to depth).
    p_cam = torch.tensor([0.0, 0.0, -2.0, 1.0], dtype=torch.float64)
    p_world = (c2w @ p_cam)[:3]
    s = math.exp(0.7)
    p_new = out[:3, :3] @ (p_cam[:3] * s) + out[:3, 3]
    assert torch.allclose(p_new, G.transform_points(T, p_world[None])[0], atol=1e-10)


def test_pose_error_and_rotation_angle():
    rot = G.so3_exp(torch.tensor([0.0, 0.0, math.radians(30)], dtype=torch.float64))
    assert float(G.rotation_angle_deg(torch.eye(3, dtype=torch.float64), rot)) == pytest.approx(30.0, abs=1e-9)
    a = torch.eye(4, dtype=torch.float64)
    b = torch.eye(4, dtype=torch.float64)
    b[:3, :3] = 2 * rot
    b[:3, 3] = torch.tensor([0.0, 3.0, 4.0])
    err = G.pose_error(b, a)
    assert err["rotation_deg"] == pytest.approx(30.0, abs=1e-9)
    assert err["translation"] == pytest.approx(5.0)
    assert err["scale_rel"] == pytest.approx(1.0)


@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_recovers_a_known_similarity(with_scale):
    g = _gen(3)
    T = G.sim3_from_params(torch.tensor(0.4 if with_scale else 0.0, dtype=torch.float64),
                           torch.tensor([2.5, -0.3, 0.4], dtype=torch.float64),
                           torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64))
    src = torch.randn(50, 3, generator=g, dtype=torch.float64)
    dst = G.transform_points(T, src)
    est = G.umeyama(src, dst, with_scale=with_scale)
    assert torch.allclose(est, T, atol=1e-9)


@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_batched_matches_umeyama_on_every_problem(with_scale):
    g = _gen(4)
    src = torch.randn(16, 5, 3, generator=g, dtype=torch.float64)
    dst = torch.randn(16, 5, 3, generator=g, dtype=torch.float64) * 2 + 1  # noisy, not exact
    batch = G.umeyama_batched(src, dst, with_scale=with_scale)
    for b in range(16):
        assert torch.allclose(batch[b], G.umeyama(src[b], dst[b], with_scale=with_scale), atol=1e-9)
    # Minimal (3-point) exact problems are solved exactly, reflections excluded.
    T = G.sim3_from_params(torch.tensor(-0.3, dtype=torch.float64), torch.tensor([0.1, 3.0, -0.2], dtype=torch.float64),
                           torch.tensor([0.5, 0.0, -4.0], dtype=torch.float64))
    pts = torch.randn(8, 3, 3, generator=g, dtype=torch.float64)
    est = G.umeyama_batched(pts, G.transform_points(T, pts.reshape(-1, 3)).reshape(8, 3, 3), with_scale=True)
    assert torch.allclose(est, T.expand(8, 4, 4), atol=1e-8)
    with pytest.raises(ValueError):
        G.umeyama_batched(torch.zeros(4, 2, 3), torch.zeros(4, 2, 3))


def test_umeyama_rejects_bad_shapes():
    with pytest.raises(ValueError):
        G.umeyama(torch.zeros(2, 3), torch.zeros(2, 3))


def test_look_at_follows_opengl_convention():
    c2w = G.look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    forward = -c2w[:3, 2]
    assert torch.allclose(forward, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    assert torch.allclose(c2w[:3, 1], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    with pytest.raises(ValueError):
        G.look_at(torch.tensor([0.0, 0.0, 4.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))


def test_unproject_depth_lands_each_pixel_on_the_point_it_sees():
    """A camera 4 units from a wall: every pixel with depth lands on the wall, where its ray meets it."""
    c2w = G.look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    intrinsics = torch.tensor([10.0, 10.0, 4.0, 3.0])  # fx, fy, cx, cy of an 8 x 6 image
    depth = torch.full((6, 8), 4.0)
    depth[0, 0] = 0.0  # unknown: skipped
    points = G.unproject_depth(depth, intrinsics, c2w)  # [47, 3]
    assert points.shape == (47, 3) and points.dtype == torch.float64
    assert torch.allclose(points[:, 1], torch.zeros(47, dtype=torch.float64), atol=1e-12)  # on the wall y = 0
    # pixel (row 5, col 7): 3.5 px right of and 2.5 px below the centre, at 4 units through fx = 10
    assert torch.allclose(points[-1], torch.tensor([1.4, 0.0, -1.0], dtype=torch.float64), atol=1e-12)
