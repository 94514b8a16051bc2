"""The occupancy grid: which cells of a known density field it keeps, and its schedule."""

from __future__ import annotations

import pytest
import torch

from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid

R = 16


def cell_bounds(r: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper corners of every cell in the flat order of OccupancyGrid.  -> ([C, 3], [C, 3])."""
    ii = torch.arange(r)
    ijk = torch.stack(torch.meshgrid(ii, ii, ii, indexing="ij"), -1).reshape(-1, 3).double()
    return ijk * (2 / r) - 1, (ijk + 1) * (2 / r) - 1


def sphere_density(x: torch.Tensor) -> torch.Tensor:
    """10 inside the sphere of radius 0.5 at (0.2, -0.1, 0), 0 outside.  [N, 3] -> [N]."""
    inside = (x - torch.tensor([0.2, -0.1, 0.0])).norm(dim=-1) < 0.5
    return inside.float() * 10


def test_cells_of_a_known_density_are_marked_occupied_or_empty():
    grid = OccupancyGrid(OccupancyConfig(resolution=R))
    grid.update(0, sphere_density, torch.Generator().manual_seed(0))
    lo, hi = cell_bounds(R)
    centre = torch.tensor([0.2, -0.1, 0.0], dtype=torch.float64)
    nearest = torch.maximum(torch.minimum(centre, hi), lo)  # closest point of each cell to the centre
    corners = torch.stack([torch.where(torch.tensor([(c >> a) & 1 for a in range(3)]).bool(), hi, lo)
                           for c in range(8)], 1)  # [C, 8, 3]
    fully_inside = ((corners - centre).norm(dim=-1) < 0.5).all(-1)
    fully_outside = (nearest - centre).norm(dim=-1) >= 0.5
    assert int(fully_inside.sum()) > 20 and int(fully_outside.sum()) > R**3 // 2
    assert bool(grid.occupied[fully_inside].all())
    assert not bool(grid.occupied[fully_outside].any())
    pts = torch.tensor([[0.2, -0.1, 0.0], [0.9, 0.9, 0.9], [-0.9, 0.0, 0.0]])
    assert grid.is_occupied(pts).tolist() == [True, False, False]


def test_threshold_is_the_smaller_of_the_mean_and_the_configured_density():
    # left half 5, right half 0.5: mean 2.75 > threshold 1 -> only the left half is kept
    grid = OccupancyGrid(OccupancyConfig(resolution=R, density_threshold=1.0))
    grid.update(0, lambda x: torch.where(x[:, 0] < 0, 5.0, 0.5))
    lo, _ = cell_bounds(R)
    assert torch.equal(grid.occupied, lo[:, 0] < 0)
    # a faint field, everywhere below the threshold: the mean decides instead (0.3 > mean ~0.21 > 0.2)
    grid = OccupancyGrid(OccupancyConfig(resolution=R, density_threshold=1.0))
    grid.update(0, lambda x: torch.where(x[:, 2] > 0.5, 0.3, 0.2))
    assert torch.equal(grid.occupied, lo[:, 2] >= 0.5)


@pytest.mark.parametrize("value", [0.0, 1e-3, 0.01, 0.05, 0.3])
def test_a_uniformly_faint_field_is_never_pruned_to_nothing(value):
    grid = OccupancyGrid(OccupancyConfig(resolution=R))
    grid.update(0, lambda x: torch.full((x.shape[0],), value))
    assert grid.occupied_fraction > 0
    assert bool(grid.is_occupied(torch.zeros(1, 3)))  # the constant field keeps its (equal) densest cells: all


def test_running_max_decays_and_empties_cells_whose_density_vanished():
    cfg = OccupancyConfig(resolution=8, decay=0.5, update_every=4, warmup_steps=10**6)  # full updates throughout
    grid = OccupancyGrid(cfg)
    lo, _ = cell_bounds(8)
    left = lo[:, 0] < 0
    grid.update(0, lambda x: torch.where(x[:, 0] < 0, 8.0, 0.0) + torch.where(x[:, 1] < 0, 4.0, 0.0))
    assert torch.equal(grid.occupied, left | (lo[:, 1] < 0))
    for step in range(1, 4):  # the y < 0 density is gone: 4 * 0.5^step
        grid.update(step, lambda x: torch.where(x[:, 0] < 0, 8.0, 0.0))
    assert torch.allclose(grid.density[~left & (lo[:, 1] < 0)], torch.tensor(0.5))
    assert torch.equal(grid.occupied, left)  # 0.5 < threshold min(mean, 1) = 1
    assert not grid.maybe_update(5, sphere_density) and grid.maybe_update(8, sphere_density)


def test_after_warmup_an_update_visits_a_random_quarter_plus_a_quarter_of_the_occupied_cells():
    cfg = OccupancyConfig(resolution=R, warmup_steps=16, update_every=16)
    grid = OccupancyGrid(cfg)
    seen: list[torch.Tensor] = []

    def recording(x: torch.Tensor) -> torch.Tensor:
        seen.append(x)
        return sphere_density(x)

    grid.update(0, recording)
    assert sum(len(x) for x in seen) == R**3  # warm-up: every cell
    occupied_before = grid.occupied.clone()
    seen.clear()
    grid.update(16, recording, torch.Generator().manual_seed(0))
    visited = grid.cell_index(torch.cat(seen))
    assert len(visited) == R**3 // 4 + int(occupied_before.sum()) // 4
    # the occupied cells are visited about twice as often as a uniform draw would visit them
    share = float(occupied_before[visited].float().mean())
    assert share > 1.6 * float(occupied_before.float().mean())


@pytest.mark.parametrize("unbounded", [False, True])
def test_open_frustum_opens_what_a_new_camera_sees_and_nothing_behind_it(unbounded):
    from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid

    grid = OccupancyGrid(OccupancyConfig(resolution=16, warmup_steps=32, update_every=16))
    grid.occupied[:] = False
    c2w = torch.eye(4)  # at the centre, looking down -z (OpenGL)
    opened = grid.open_frustum(c2w, torch.tensor([8.0, 8.0, 8.0, 8.0]), 16, 16, unbounded, step=100)
    centres = (grid._cell_xyz.float() + 0.5) * (2.0 / 16) - 1
    ahead = (centres[:, 2] < -0.1) & (centres[:, :2].abs() < 0.5 * -centres[:, 2:3]).all(-1)
    behind = centres[:, 2] > 0.1
    assert opened == int(grid.occupied.sum()) > 0
    assert bool(grid.occupied[ahead].all()) and not bool(grid.occupied[behind].any())
    grid.occupied[:] = False  # the field pruned it since: a second camera there reopens nothing it saw
    assert grid.open_frustum(c2w, torch.tensor([8.0, 8.0, 8.0, 8.0]), 16, 16, unbounded, step=100) == 0
    turned = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0]))  # looking the other way: all new
    assert grid.open_frustum(turned, torch.tensor([8.0, 8.0, 8.0, 8.0]), 16, 16, unbounded, step=100) > 0
    assert bool(grid.occupied[behind & (centres[:, :2].abs() < 0.5 * centres[:, 2:3]).all(-1)].all())


def test_opened_cells_are_held_for_a_warm_up_then_judged_by_the_field_without_moving_the_threshold():
    """Opened with a forced density instead, they raised the mean that sets the threshold until the
    field's own faint cells were pruned: streamed training stalled (bench_stream.py --sampling)."""
    from agent.nerf.occupancy import OccupancyConfig, OccupancyGrid

    grid = OccupancyGrid(OccupancyConfig(resolution=16, warmup_steps=32, update_every=16))
    centres = (grid._cell_xyz.float() + 0.5) * (2.0 / 16) - 1
    ahead = (centres[:, 2] < -0.1) & (centres[:, :2].abs() < 0.5 * -centres[:, 2:3]).all(-1)
    solid = (centres[:, 2] > 0.5) & (centres[:, :2].abs() < 0.3).all(-1)  # a faint object behind the camera

    def field(x):  # density 0.2 in the object, 0 elsewhere (the new camera's space not learnt yet)
        return 0.2 * ((x[:, 2] > 0.5) & (x[:, :2].abs() < 0.3).all(-1)).float()

    grid.update(0, field)  # warm-up: every cell judged
    assert bool(grid.occupied[solid].all()) and not bool(grid.occupied[ahead].any())
    grid.open_frustum(torch.eye(4), torch.tensor([8.0, 8.0, 8.0, 8.0]), 16, 16, False, step=100)
    for step in (112, 128):  # held until step 132 although the field is empty there ...
        grid.update(step, field)
        assert bool(grid.occupied[ahead].all())
        assert bool(grid.occupied[solid].all())  # ... and the faint object is not pruned for them
    grid.update(144, field)  # then judged (every held cell is visited) and pruned
    assert not bool(grid.occupied[ahead].any()) and bool(grid.occupied[solid].all())
