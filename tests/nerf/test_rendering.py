"""Volume rendering of known densities, the packed-sample helpers, and marching with early termination."""

from __future__ import annotations

import math

import pytest
import torch

from agent.nerf.losses import distortion_loss
from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid
from agent.nerf.rays import Rays, pixel_rays
from agent.nerf.renderer import composite, render_rays
from agent.nerf.sampler import MarchConfig, Samples, exclusive_segment_cumsum, march, ray_box_intersection

D = torch.float64


def uniform_samples(counts: list[int], dt: float) -> Samples:
    """Packed samples: ray r gets counts[r] segments [k dt, (k+1) dt).  -> S = sum(counts)."""
    ray_index = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))  # [S]
    k = torch.cat([torch.arange(c, dtype=D) for c in counts])  # [S] rank within the ray
    return Samples(ray_index, (k + 0.5) * dt, torch.full_like(k, dt), len(counts))


def test_a_homogeneous_slab_gives_the_analytic_opacity_depth_and_colour():
    a, b, sigma, dt = 0.7, 1.9, 2.3, 1e-3
    far = 3.0
    counts = [round(far / dt), 0, round(far / dt)]  # ray 1 has no sample at all; ray 2 sees an empty scene
    samples = uniform_samples(counts, dt)
    t = samples.t_mid
    in_slab = (t > a) & (t < b)
    density = (in_slab & (samples.ray_index == 0)).to(D) * sigma  # [S]
    mid = (a + b) / 2
    red, blue = torch.tensor([1.0, 0, 0], dtype=D), torch.tensor([0, 0, 1.0], dtype=D)
    rgb = torch.where((t < mid)[:, None], red, blue)  # [S, 3]: front half red, back half blue
    color, dist, opacity, _, _ = composite(density, rgb, samples)  # [R, 3], [R], [R]

    thick = b - a
    assert float(opacity[0]) == pytest.approx(1 - math.exp(-sigma * thick), abs=1e-9)
    # E[t; hit] = int_a^b t sigma exp(-sigma (t - a)) dt
    expected = a * (1 - math.exp(-sigma * thick)) + 1 / sigma - math.exp(-sigma * thick) * (thick + 1 / sigma)
    assert float(dist[0]) == pytest.approx(expected, abs=1e-5)
    half = math.exp(-sigma * thick / 2)  # transmittance through one half of the slab
    assert torch.allclose(color[0], (1 - half) * red + half * (1 - half) * blue, atol=1e-9)
    for empty in (1, 2):
        assert float(opacity[empty]) == 0 and float(dist[empty]) == 0 and float(color[empty].abs().sum()) == 0


def test_composite_gradients_reach_density_and_colour():
    samples = uniform_samples([50, 30], 0.02)
    sigma = torch.full((80,), 3.0, dtype=D, requires_grad=True)
    rgb = torch.rand(80, 3, dtype=D, generator=torch.Generator().manual_seed(0), requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, c: torch.cat([x.reshape(-1) for x in composite(s, c, samples)[:3]]),
                                    (sigma, rgb))


def test_exclusive_segment_cumsum_matches_a_loop():
    g = torch.Generator().manual_seed(0)
    counts = torch.randint(0, 6, (40,), generator=g)  # [R], zeros included: rays without samples
    counts[-1] = 0
    ray_index = torch.repeat_interleave(torch.arange(40), counts)  # [S] sorted
    values = torch.rand(ray_index.numel(), generator=g) * 1000  # large values: global cumsum round-off shows
    out = exclusive_segment_cumsum(values, ray_index, 40)
    expected = torch.empty_like(values)
    running: dict[int, float] = {}
    for i, (v, r) in enumerate(zip(values.tolist(), ray_index.tolist())):
        expected[i] = running.get(r, 0.0)
        running[r] = running.get(r, 0.0) + v
    assert out.shape == values.shape and out.dtype == values.dtype
    assert torch.allclose(out, expected, rtol=0, atol=1e-3)
    assert float(out[torch.cumsum(counts, 0)[counts > 0] - counts[counts > 0]].abs().max()) == 0  # first of each ray


def test_exclusive_segment_cumsum_keeps_small_per_ray_sums_exact_after_many_rays():
    # 100k opaque rays (optical depth 1e3 each) before one faint ray: the global running sum reaches 1e8,
    # where a float32 ulp is 8, so a float32 cumsum would return 0, 0, 0 for the faint ray
    ray_index = torch.cat([torch.arange(100_000), torch.full((3,), 100_000)])
    values = torch.cat([torch.full((100_000,), 1e3), torch.tensor([0.1, 0.2, 0.3])])
    out = exclusive_segment_cumsum(values, ray_index, 100_001)
    assert torch.allclose(out[-3:], torch.tensor([0.0, 0.1, 0.3]), rtol=1e-6, atol=0)


def test_ray_box_intersection_on_known_rays_and_against_dense_sampling():
    o = torch.tensor([[0.0, 0, 3], [0.5, 0.5, 0], [2.0, 0, 0], [3, 3, 3]], dtype=D)
    d = torch.tensor([[0.0, 0, -1], [1.0, 0, 0], [0, 1.0, 0], [-1, -1, -1]], dtype=D)
    d = d / d.norm(dim=-1, keepdim=True)
    near, far = ray_box_intersection(o, d)
    assert torch.allclose(near[:2], torch.tensor([2.0, -1.5], dtype=D)) and torch.allclose(far[:2], torch.tensor([4.0, 0.5], dtype=D))
    assert float(far[2]) < float(near[2])  # parallel to y, outside the x slab: a miss
    assert float(near[3]) == pytest.approx(2 * math.sqrt(3)) and float(far[3]) == pytest.approx(4 * math.sqrt(3))

    g = torch.Generator().manual_seed(1)
    o = (torch.rand(300, 3, generator=g, dtype=D) - 0.5) * 6
    d = torch.randn(300, 3, generator=g, dtype=D)
    d = d / d.norm(dim=-1, keepdim=True)
    near, far = ray_box_intersection(o, d)
    t = torch.linspace(-12, 12, 24001, dtype=D)  # [K] step 1e-3
    pts = o[:, None] + t[None, :, None] * d[:, None]  # [300, K, 3]
    inside = (pts.abs() <= 1).all(-1)  # [300, K]
    hit = inside.any(-1)
    assert bool((hit == (far >= near)).all())
    first = torch.where(hit, t[inside.float().argmax(-1)], 0)
    last = torch.where(hit, t[inside.shape[1] - 1 - inside.flip(-1).float().argmax(-1)], 0)
    assert torch.allclose(near[hit], first[hit], atol=2e-3) and torch.allclose(far[hit], last[hit], atol=2e-3)


class CountingDensity:
    """An opaque half-space z < wall (density 1e4) behind empty space; counts the points evaluated."""

    def __init__(self, wall: float) -> None:
        self.wall = wall
        self.evaluated = 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [N]
        self.evaluated += x.shape[0]
        return torch.where(x[:, 2] < self.wall, 1e4, 0.0).to(x.dtype)


def test_march_keeps_exactly_the_samples_in_front_of_the_surface_and_none_in_empty_cells():
    r = 16
    grid = OccupancyGrid(OccupancyConfig(resolution=r))
    cells = torch.arange(r**3)
    z_cell = cells % r  # flat index is (i r + j) r + k with k the z cell
    empty_band = (z_cell >= 12) & (z_cell < 14)  # z in [0.5, 0.75): marked empty
    grid.occupied = ~empty_band
    cfg = MarchConfig(step_size=0.01, early_stop_eps=1e-4, first_wave=4)  # many waves per ray
    g = torch.Generator().manual_seed(0)
    n = 64
    origins = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 1.2, torch.full((n, 1), 3.0)], -1)  # above the box
    directions = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.2, -torch.ones(n, 1)], -1)  # all hit the wall
    directions = directions / directions.norm(dim=-1, keepdim=True)  # [n, 3] downwards
    origins[-1] = torch.tensor([5.0, 5.0, 3.0])  # misses the box
    wall = 0.2
    density = CountingDensity(wall)
    samples = march(origins, directions, grid, density, cfg)

    near, far = ray_box_intersection(origins, directions)
    total_candidates = 0
    for ray in range(n):
        kept = samples.t_mid[samples.ray_index == ray]
        if ray == n - 1:
            assert kept.numel() == 0
            continue
        k = torch.arange(int(torch.ceil((far[ray] - near[ray]) / cfg.step_size)))
        t = near[ray] + (k + 0.5) * cfg.step_size
        t = t[t < far[ray]]
        z = origins[ray, 2] + t * directions[ray, 2]
        total_candidates += t.numel()
        z_index = ((z + 1) * r / 2).long().clamp(0, r - 1)
        occupied = ~((z_index >= 12) & (z_index < 14))
        t, z = t[occupied], z[occupied]
        behind = (z < wall).nonzero()
        stop = int(behind[0]) + 1 if behind.numel() else t.numel()  # the first sample in the wall is kept
        expected = t[:stop]
        assert kept.numel() == expected.numel(), ray
        assert torch.allclose(kept, expected, atol=1e-5)
    pts = origins[samples.ray_index] + samples.t_mid[:, None] * directions[samples.ray_index]
    assert not bool(grid.is_occupied(pts).logical_not().any())  # no sample in an empty cell
    assert int((pts[:, 2] < wall).sum()) == n - 1  # one sample per (hitting) ray inside the wall
    # early termination: far fewer points were evaluated than the candidates in occupied cells
    assert density.evaluated < 0.5 * total_candidates


def test_march_without_termination_keeps_every_occupied_candidate():
    grid = OccupancyGrid(OccupancyConfig(resolution=8))
    origins = torch.tensor([[0.1, 0.2, 3.0], [0.3, -0.4, -3.0]])
    directions = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    samples = march(origins, directions, grid, lambda x: torch.full((x.shape[0],), 0.01), MarchConfig(step_size=0.1))
    assert samples.ray_index.tolist() == [0] * 20 + [1] * 20  # 2 box units / 0.1, sorted by ray
    assert torch.allclose(samples.t_mid[:20], 2.05 + 0.1 * torch.arange(20))


class SlabField:
    """A stand-in for NGPField: an opaque slab below z = wall (box coordinates), grey, no parameters."""

    def __init__(self, wall: float) -> None:
        self.wall = wall

    def density(self, x, level_weights=None):  # [N, 3] -> ([N], [N, 1])
        return torch.where(x[:, 2] < self.wall, 1e5, 0.0), x[:, :1]  # opaque within one 1e-3 step

    def __call__(self, x, dirs, level_weights=None):  # -> ([N], [N, 3])
        return self.density(x)[0], torch.full_like(x, 0.5)


def test_render_rays_reports_z_depth_in_the_frame_of_the_rays():
    """A camera 6 units above a floor at z = 0 of a frame whose box is scaled by 1/4: depth 6 everywhere."""
    box_from_frame = torch.eye(4)
    box_from_frame[:3, :3] *= 0.25  # frame [-4, 4]^3 -> box [-1, 1]^3
    box_from_frame[2, 3] = -0.5  # frame z = 2 -> box z = 0; the floor z = 0 -> box z = -0.5
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 6.0])  # looks down -Z at the floor
    w = h = 9
    ii, jj = torch.meshgrid(torch.arange(w) + 0.5, torch.arange(h) + 0.5, indexing="xy")
    rays = pixel_rays(c2w.expand(w * h, 4, 4), torch.tensor([12.0, 12.0, 4.5, 4.5]).expand(w * h, 4),
                      ii.reshape(-1), jj.reshape(-1))
    grid = OccupancyGrid(OccupancyConfig(resolution=16))
    out = render_rays(SlabField(-0.5), grid, rays, torch.ones(3), MarchConfig(step_size=1e-3), box_from_frame)
    assert torch.allclose(out.opacity, torch.ones(w * h), atol=1e-4)
    # the first sample inside the floor takes all the weight; it is at most one step (1e-3 box = 4e-3 frame
    # units along the ray) past the floor, so the z-depth is in [6, 6.004]
    assert float(out.depth.min()) >= 6.0 - 1e-5 and float(out.depth.max()) <= 6.0 + 4.1e-3
    assert torch.allclose(out.rgb, torch.full((w * h, 3), 0.5), atol=1e-3)
    off_axis = out.depth[0] / rays.z_per_t[0]  # distance along the corner ray is longer than the depth
    assert float(off_axis) > 6.0 * 1.02


def test_render_rays_composites_onto_the_background_where_nothing_is_hit():
    rays = Rays(torch.tensor([[0.0, 0, 5], [0.0, 0, 5]]), torch.tensor([[0.0, 0, -1], [0.0, 1, 0]]), torch.ones(2))
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.7, 0.8, 0.9]])  # [R, 3] per-pixel (random) background
    box = torch.eye(4)
    box[:3, :3] *= 0.5
    out = render_rays(SlabField(0.0), OccupancyGrid(OccupancyConfig(resolution=8)), rays, bg,
                      MarchConfig(step_size=1e-2), box)
    assert torch.allclose(out.rgb[0], torch.full((3,), 0.5), atol=1e-4)  # hits the slab: its grey
    assert torch.allclose(out.rgb[1], bg[1]) and float(out.opacity[1]) == 0  # misses the box: background


def test_distortion_loss_is_the_double_sum_and_prefers_one_compact_interval():
    """The linear-time form equals mip-NeRF 360's double sum over every ray's samples, and the same
    opacity concentrated at one depth costs less than spread over the ray (a floater in front)."""
    gen = torch.Generator().manual_seed(3)
    counts = [5, 1, 9]
    idx = torch.repeat_interleave(torch.arange(3), torch.tensor(counts))
    t = torch.cat([torch.sort(torch.rand(c, generator=gen) * 6)[0] for c in counts])
    dt = torch.rand(len(t), generator=gen) * 0.1 + 0.01
    w = torch.rand(len(t), generator=gen, dtype=torch.float64).float()
    samples = Samples(ray_index=idx, t_mid=t, dt=dt, num_rays=3)
    want = 0.0
    for r in range(3):
        m = idx == r
        s, ds, wr = t[m] / (1 + t[m]), dt[m] / (1 + t[m]) ** 2, w[m]
        want += float((wr[:, None] * wr[None, :] * (s[:, None] - s[None, :]).abs()).sum() + (wr**2 * ds).sum() / 3)
    assert abs(float(distortion_loss(w, samples)) - want / 3) < 1e-5
    t2 = torch.linspace(0.5, 5.0, 10)
    one = Samples(ray_index=torch.zeros(10, dtype=torch.long), t_mid=t2, dt=torch.full((10,), 0.05), num_rays=1)
    compact = torch.zeros(10)
    compact[7] = 0.9
    spread = torch.full((10,), 0.09)
    assert float(distortion_loss(compact, one)) < float(distortion_loss(spread, one)) / 10


def test_the_evaluation_renderer_composites_what_training_does_evaluating_each_sample_once():
    from agent.nerf.field import FieldConfig, NGPField
    from agent.nerf.rays import image_rays
    from agent.nerf.renderer import render_rays_eval

    torch.manual_seed(0)
    for unbounded in (False, True):
        field = NGPField(FieldConfig(unbounded=unbounded, density_bias=1.0))  # a dense fog: rays end early
        grid = OccupancyGrid(OccupancyConfig(resolution=16))
        c2w = torch.eye(4)
        c2w[:3, 3] = torch.tensor([0.1, 0.2, 0.8])
        rays = image_rays(c2w, torch.tensor([20.0, 20.0, 8.0, 8.0]), 16, 16)
        cfg = MarchConfig(step_size=0.02)
        with torch.no_grad():
            two_pass = render_rays(field, grid, rays, torch.ones(3), cfg, torch.eye(4))
        one_pass = render_rays_eval(field, grid, rays, torch.ones(3), cfg, torch.eye(4))
        assert torch.allclose(one_pass.rgb, two_pass.rgb, atol=2e-4)  # up to what lies past termination
        assert torch.allclose(one_pass.opacity, two_pass.opacity, atol=2e-4)
        assert torch.allclose(one_pass.depth, two_pass.depth, atol=2e-3)
        assert 0 < one_pass.num_samples < 2 * two_pass.num_samples  # each evaluated once, a wave's overshoot at most
