"""Multiresolution hash encoding (instant-NGP) laid out for speed on the CPU.

What made it fast here (docs/design.md, "NeRF facts"):
the point index is the innermost dimension (``[L, 8, N]``), indices are built per axis and
combined (the dense and hashed indices are both separable), and the table lookup is a small
custom autograd function whose backward is a ``scatter_add_`` rather than advanced indexing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from agent.config_io import InvalidValue, check

# Spatial-hash primes of instant-NGP, as int32 (wrap-around multiplication is the hash).
_PRIMES_I32 = (1, 2654435761 - 2**32, 805459861)
HASH_PRIMES = tuple(p % 2**32 for p in _PRIMES_I32)  # the same, unsigned (for exports that other programs read)


@dataclass
class HashGridConfig:
    num_levels: int = 16
    features_per_level: int = 2
    log2_hashmap_size: int = 17
    base_resolution: int = 16
    max_resolution: int = 1024
    init_scale: float = 1e-4  # tables start near zero so the MLP sees a smooth field

    def __post_init__(self) -> None:
        check(self, num_levels=">= 1", features_per_level=">= 1", log2_hashmap_size="in [8, 24]",
              base_resolution=">= 2", init_scale=">= 0")
        if not self.base_resolution <= self.max_resolution:
            raise InvalidValue("max_resolution", f"must be >= base_resolution ({self.base_resolution}), "
                               f"got {self.max_resolution!r}")

    @property
    def output_dim(self) -> int:
        return self.num_levels * self.features_per_level

    def resolutions(self) -> list[int]:
        if self.num_levels == 1:
            return [self.base_resolution]
        growth = math.exp((math.log(self.max_resolution) - math.log(self.base_resolution)) / (self.num_levels - 1))
        # + 1e-6: exp/log round-off must not floor the finest level to max_resolution - 1 (1023 for 1024)
        return [int(math.floor(self.base_resolution * growth**level + 1e-6)) for level in range(self.num_levels)]


class _Gather(torch.autograd.Function):
    """``table[index]`` with a cheap scatter-add backward.

    On the CPU, autograd's backward of advanced indexing sorts the indices, and ``index_add_``
    over rows of F=2 floats pays a slice per row (~8x slower here); ``scatter_add_`` with an
    expanded (never materialised) index is the fast path.
    """

    @staticmethod
    def forward(ctx, table: Tensor, index: Tensor) -> Tensor:  # table: [T, F], index: [K] int64 -> [K, F]
        ctx.save_for_backward(index)
        ctx.table_shape = table.shape
        return table.index_select(0, index)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # grad_out: [K, F]
        (index,) = ctx.saved_tensors
        grad_table = grad_out.new_zeros(ctx.table_shape)
        grad_table.scatter_add_(0, index[:, None].expand_as(grad_out), grad_out.contiguous())
        return grad_table, None


class HashGrid(nn.Module):
    """``x [N, 3] in [0, 1]^3 -> features [N, L * F]``, trilinear within each level.

    Coarse levels whose grid fits in the table are indexed densely (no collisions); finer ones
    are hashed. All levels share one flat parameter ``table: [L * T, F]`` so that consensus sees
    a single tensor and the lookup is a single gather.

    Both index kinds are separable per axis (``a_x + a_y + a_z`` dense, ``a_x ^ a_y ^ a_z``
    hashed), so each axis term is computed once for the two corner offsets ``[L, 2, N]`` and
    the eight corners are combined from them, instead of multiplying ``[L, 3, 8, N]`` coordinates.
    """

    def __init__(self, cfg: HashGridConfig) -> None:
        super().__init__()
        self.cfg = cfg
        table_size = 2**cfg.log2_hashmap_size
        res = cfg.resolutions()
        self.table_size = table_size
        self.table = nn.Parameter(
            (torch.rand(cfg.num_levels * table_size, cfg.features_per_level) * 2 - 1) * cfg.init_scale
        )
        dense = [(r + 1) ** 3 <= table_size for r in res]
        # Levels are processed in two groups (dense first, then hashed); remember the order.
        self.dense_levels = [i for i, d in enumerate(dense) if d]
        self.hashed_levels = [i for i, d in enumerate(dense) if not d]
        order = self.dense_levels + self.hashed_levels
        self.register_buffer("inverse_order", torch.argsort(torch.tensor(order)), persistent=False)  # [L]
        self.register_buffer(
            "resolution", torch.tensor([res[i] for i in order], dtype=torch.float32), persistent=False
        )  # [L] in group order
        mult = [[1, res[i] + 1, (res[i] + 1) ** 2] for i in self.dense_levels]
        mult += [list(_PRIMES_I32) for _ in self.hashed_levels]
        self.register_buffer(
            "mult", torch.tensor(mult, dtype=torch.int32).T.contiguous()[:, :, None], persistent=False
        )  # [3, L, 1]
        self.register_buffer(
            "level_offset", (torch.tensor(order, dtype=torch.int32) * table_size)[:, None, None], persistent=False
        )  # [L, 1, 1]

    @property
    def output_dim(self) -> int:
        return self.cfg.output_dim

    def _corner_index(self, base: Tensor) -> Tensor:
        """base: [3, L, N] int32 lower corners -> table rows [L, 8, N] (corner bits: x=1, y=2, z=4)."""
        terms = []
        for axis in range(3):
            a0 = base[axis] * self.mult[axis]  # [L, N]
            terms.append(torch.stack([a0, a0 + self.mult[axis]], 1))  # [L, 2, N]
        tx = terms[0][:, None, None, :, :]  # [L, 1, 1, 2, N]  (x bit varies fastest)
        ty = terms[1][:, None, :, None, :]  # [L, 1, 2, 1, N]
        tz = terms[2][:, :, None, None, :]  # [L, 2, 1, 1, N]
        n = base.shape[-1]
        nd = len(self.dense_levels)
        parts = []
        if nd:
            parts.append((tx[:nd] + ty[:nd] + tz[:nd]).reshape(nd, 8, n))
        if self.hashed_levels:
            parts.append(torch.bitwise_xor(torch.bitwise_xor(tx[nd:], ty[nd:]), tz[nd:]).reshape(len(self.hashed_levels), 8, n))
        idx = torch.cat(parts) if len(parts) > 1 else parts[0]
        return torch.bitwise_and(idx, self.table_size - 1) + self.level_offset  # [L, 8, N]

    def forward(self, x: Tensor, level_weights: Tensor | None = None) -> Tensor:
        """x: [N, 3] in [0, 1]; level_weights: [L] in [0, 1] (coarse-to-fine mask) -> [N, L*F]."""
        n = x.shape[0]
        levels, feats = self.cfg.num_levels, self.cfg.features_per_level
        pos = x.T[:, None, :] * self.resolution[None, :, None]  # [3, L, N], differentiable in x
        base = torch.floor(pos.detach())
        idx = self._corner_index(base.to(torch.int32))  # [L, 8, N]
        corner_feats = _Gather.apply(self.table, idx.reshape(-1).long()).view(levels, 8, n, feats)

        frac = pos - base  # [3, L, N]
        w = torch.stack([1 - frac, frac], 2)  # [3, L, 2, N]
        weights = w[2][:, :, None, None, :] * w[1][:, None, :, None, :] * w[0][:, None, None, :, :]
        weights = weights.reshape(levels, 8, n)  # same corner order as the indices
        out = (corner_feats * weights[..., None]).sum(1)  # [L, N, F] in group order
        out = out.index_select(0, self.inverse_order)  # back to level order
        if level_weights is not None:
            out = out * level_weights[:, None, None]
        return out.permute(1, 0, 2).reshape(n, levels * feats)
