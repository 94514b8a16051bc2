"""The hash encoding against a naive per-level reference, and its gradients."""

from __future__ import annotations

import pytest
import torch

from agent.nerf.encoding import HashGrid, HashGridConfig

PRIMES = (1, 2654435761, 805459861)  # instant-NGP's spatial hash


def reference_rows(cfg: HashGridConfig, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The instant-NGP definition, one level and one corner at a time, in int64 / float64.

    x: [N, 3] in [0, 1] -> (rows [L, 8, N] into the flat table, trilinear weights [L, 8, N]).
    Level l has resolution floor(base * b**l); a level whose (res+1)^3 vertices fit the table
    is indexed densely (x + y (res+1) + z (res+1)^2), otherwise by (x*p0 ^ y*p1 ^ z*p2) mod T.
    """
    table = 2**cfg.log2_hashmap_size
    growth = (cfg.max_resolution / cfg.base_resolution) ** (1 / max(cfg.num_levels - 1, 1))
    rows, weights = [], []
    for level in range(cfg.num_levels):
        res = int(cfg.base_resolution * growth**level + 1e-9)
        pos = x.double() * res  # [N, 3]
        low = pos.floor().long()
        frac = pos - low
        level_rows, level_w = [], []
        for corner in range(8):
            bits = torch.tensor([(corner >> a) & 1 for a in range(3)])  # x bit 1, y bit 2, z bit 4
            c = low + bits  # [N, 3]
            if (res + 1) ** 3 <= table:
                idx = c[:, 0] + c[:, 1] * (res + 1) + c[:, 2] * (res + 1) ** 2
            else:
                idx = (c[:, 0] * PRIMES[0]) ^ (c[:, 1] * PRIMES[1]) ^ (c[:, 2] * PRIMES[2])
            level_rows.append(level * table + idx % table)
            w = torch.where(bits.bool(), frac, 1 - frac).prod(-1)  # [N]
            level_w.append(w)
        rows.append(torch.stack(level_rows))
        weights.append(torch.stack(level_w))
    return torch.stack(rows), torch.stack(weights)


def reference_encode(grid: HashGrid, x: torch.Tensor) -> torch.Tensor:
    """Plain advanced indexing + autograd.  x: [N, 3] -> [N, L * F] (float64)."""
    rows, w = reference_rows(grid.cfg, x)  # [L, 8, N]
    feats = grid.table.double()[rows]  # [L, 8, N, F]
    out = (feats * w[..., None]).sum(1)  # [L, N, F]
    return out.permute(1, 0, 2).reshape(x.shape[0], -1)


# dense only; dense coarse + hashed fine (the usual case); hashed only
CONFIGS = {
    "dense": HashGridConfig(num_levels=3, features_per_level=2, log2_hashmap_size=14, base_resolution=4,
                            max_resolution=16),
    "mixed": HashGridConfig(num_levels=6, features_per_level=3, log2_hashmap_size=10, base_resolution=4,
                            max_resolution=96),
    "hashed": HashGridConfig(num_levels=2, features_per_level=2, log2_hashmap_size=8, base_resolution=40,
                             max_resolution=300),
}


def make_grid(cfg: HashGridConfig, seed: int = 0) -> HashGrid:
    torch.manual_seed(seed)
    grid = HashGrid(cfg)
    with torch.no_grad():
        grid.table.uniform_(-1, 1)  # large values: a wrong row or weight cannot hide under the init scale
    return grid


def random_points(n: int, seed: int) -> torch.Tensor:
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed))
    x[:4] = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [0.999999, 1e-7, 0.5]])  # box edges
    return x


@pytest.mark.parametrize("name", CONFIGS)
def test_reference_levels_are_dense_or_hashed_as_intended(name):
    cfg = CONFIGS[name]
    grid = HashGrid(cfg)
    res = cfg.resolutions()
    dense = [(r + 1) ** 3 <= 2**cfg.log2_hashmap_size for r in res]
    assert {"dense": all(dense), "hashed": not any(dense), "mixed": any(dense) and not all(dense)}[name]
    assert grid.dense_levels == [i for i, d in enumerate(dense) if d]


@pytest.mark.parametrize("name", CONFIGS)
def test_encoding_matches_the_naive_per_level_reference(name):
    cfg = CONFIGS[name]
    grid = make_grid(cfg)
    x = random_points(500, seed=1)  # [N, 3]
    out = grid(x)
    assert out.shape == (500, cfg.num_levels * cfg.features_per_level)
    # float32 positions at resolution ~300 carry ~2e-5 of round-off in the weights; a wrong row costs ~1
    assert torch.allclose(out.double(), reference_encode(grid, x), atol=2e-4)


@pytest.mark.parametrize("name", CONFIGS)
def test_table_gradient_lands_on_the_touched_rows_and_matches_advanced_indexing(name):
    cfg = CONFIGS[name]
    grid = make_grid(cfg)
    x = random_points(16, seed=2)[4:]  # interior points (every corner weight is non-zero), few enough to leave rows untouched
    upstream = torch.randn(x.shape[0], cfg.num_levels * cfg.features_per_level,
                           generator=torch.Generator().manual_seed(3))  # [N, L*F]
    (grid(x) * upstream).sum().backward()
    ours = grid.table.grad.clone()  # [L*T, F]

    table = grid.table.detach().double().requires_grad_(True)
    rows, w = reference_rows(cfg, x)
    ref = (table[rows] * w[..., None]).sum(1).permute(1, 0, 2).reshape(x.shape[0], -1)
    (ref * upstream.double()).sum().backward()
    assert torch.allclose(ours.double(), table.grad, atol=2e-4)

    touched = torch.zeros(table.shape[0], dtype=torch.bool)
    touched[rows.reshape(-1)] = True
    assert int((~touched).sum()) > table.shape[0] // 2
    assert float(ours[~touched].abs().max()) == 0.0
    assert bool((ours[touched].abs().sum(-1) > 0).all())


def test_gradient_with_respect_to_x_matches_finite_differences():
    grid = make_grid(CONFIGS["mixed"]).double()
    x = random_points(20, seed=4)[4:].double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: grid(p), (x,), eps=1e-7, atol=1e-5)
    grid(x).sum().backward()
    assert float(x.grad.abs().min()) > 0


def test_level_weights_mask_levels_and_their_gradients():
    cfg = CONFIGS["mixed"]
    grid = make_grid(cfg)
    x = random_points(200, seed=5)
    f = cfg.features_per_level
    full = grid(x).detach()
    w = torch.tensor([1.0, 1.0, 0.5, 0.0, 0.0, 0.0])
    out = grid(x, w)
    for level in range(cfg.num_levels):
        cols = slice(level * f, (level + 1) * f)
        assert torch.allclose(out[:, cols], w[level] * full[:, cols])
    out.sum().backward()
    size = 2**cfg.log2_hashmap_size
    per_level = grid.table.grad.reshape(cfg.num_levels, size, f).abs().sum((1, 2))  # [L]
    assert bool((per_level[:3] > 0).all()) and float(per_level[3:].max()) == 0.0


@pytest.mark.parametrize(("levels", "base", "finest"), [(16, 16, 1024), (2, 40, 300), (8, 8, 128), (16, 16, 2048), (1, 16, 16)])
def test_the_coarsest_and_finest_levels_have_the_configured_resolutions(levels, base, finest):
    res = HashGridConfig(num_levels=levels, base_resolution=base, max_resolution=finest).resolutions()
    assert len(res) == levels and res[0] == base and res[-1] == finest
    assert res == sorted(res)
