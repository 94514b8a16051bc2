"""Unbounded fields: contraction of space and the cone-stepped march out to the far plane."""

from __future__ import annotations

import torch

from agent.nerf.contraction import contract
from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid
from agent.nerf.sampler import MarchConfig, _cone, march


def test_contraction_keeps_the_box_linear_and_squeezes_the_rest_into_the_cube():
    inside = torch.rand(100, 3) * 2 - 1
    assert torch.equal(contract(inside), inside * 0.5)
    far = torch.randn(1000, 3) * 1e4
    g = contract(far)
    assert float(g.abs().max()) <= 1.0 and float(g.abs().amax(-1).min()) > 0.5
    # monotone along a ray leaving the box: farther points land farther out
    t = torch.linspace(0.5, 1e3, 500)[:, None]
    ray = contract(t * torch.tensor([[0.3, 0.8, -0.52]]))
    radius = ray.abs().amax(-1)
    assert bool((radius[1:] >= radius[:-1]).all()) and float(radius[-1]) > 0.99


def test_cone_steps_tile_the_interval_without_gaps():
    a = torch.tensor([0.0, 0.3, 5.0, 2.0])
    b = torch.tensor([40.0, 3.1, 900.0, 1.0])  # the last interval is empty
    ray, t_mid, dt, rank = _cone(a, b, step=0.05, cone=1 / 32, jitter=None)
    for r in range(3):
        sel = ray == r
        covered = float(dt[sel].sum())
        assert abs(covered - float(b[r] - a[r])) <= float(dt[sel].max()), (r, covered)
        assert bool((t_mid[sel][1:] > t_mid[sel][:-1]).all()) and torch.equal(rank[sel], torch.arange(int(sel.sum())))
        # steps never shrink below the minimum and grow about with the distance
        assert float(dt[sel].min()) >= 0.05 - 1e-6 and float((dt[sel] / t_mid[sel]).max()) <= 1 / 32 + 0.05 / float(t_mid[sel].min())
    assert int((ray == 3).sum()) == 0
    assert int((ray == 2).sum()) < 250  # 5 -> 900 units in a couple of hundred steps, not 18,000


def test_an_unbounded_march_reaches_the_far_plane_and_keeps_rays_packed():
    origins = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    dirs = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    grid = OccupancyGrid(OccupancyConfig(resolution=16))  # everything occupied before any update
    s = march(origins, dirs, grid, lambda x: torch.zeros(len(x)), MarchConfig(step_size=0.05, far=100.0),
              visibility=False, to_grid=contract)
    assert bool((s.ray_index[1:] >= s.ray_index[:-1]).all())
    for r in range(2):
        t = s.t_mid[s.ray_index == r]
        assert bool((t[1:] > t[:-1]).all()) and float(t.max()) > 90.0
    inside = s.t_mid[(s.ray_index == 0) & (s.t_mid > 2.0) & (s.t_mid < 4.0)]
    assert torch.allclose(inside[1:] - inside[:-1], torch.full((len(inside) - 1,), 0.05), atol=1e-4)  # uniform in the box
