"""Occupancy grid for empty-space skipping: what makes NeRF training fast enough on a CPU.

A cell is occupied when the field's density there (a running max with decay) exceeds a
threshold. The schedule follows nerfacc: every ``update_every`` steps, all cells during warm-up,
afterwards a random quarter of all cells plus a quarter of the occupied ones. The threshold is
``min(mean density, density_threshold)`` so that a young, uniformly faint field is never pruned
to nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from agent.config_io import check


@dataclass
class OccupancyConfig:
    resolution: int = 64
    density_threshold: float = 1.0  # in box units: density above which a cell is kept
    decay: float = 0.95
    update_every: int = 16
    warmup_steps: int = 256

    def __post_init__(self) -> None:
        check(self, resolution=">= 1", decay="in [0, 1]", update_every=">= 1", warmup_steps=">= 0")


class OccupancyGrid:
    """A ``resolution^3`` grid over the box ``[-1, 1]^3``."""

    def __init__(self, cfg: OccupancyConfig, device: torch.device | str = "cpu") -> None:
        self.cfg = cfg
        r = cfg.resolution
        self.device = torch.device(device)
        self.density = torch.full((r**3,), -1.0, device=self.device)  # [C] running max; -1 = never seen
        self.occupied = torch.ones(r**3, dtype=torch.bool, device=self.device)  # [C]
        ii = torch.arange(r, device=self.device)
        grid = torch.stack(torch.meshgrid(ii, ii, ii, indexing="ij"), -1).reshape(-1, 3)  # [C, 3] (x, y, z)
        self._cell_xyz = grid.to(torch.int32)
        self.seen = torch.zeros(r**3, dtype=torch.bool, device=self.device)  # [C] in some admitted camera's view
        self.open_until = torch.zeros(r**3, dtype=torch.long, device=self.device)  # [C] held open before this step

    # --- queries -------------------------------------------------------------------------
    def cell_index(self, x: Tensor) -> Tensor:
        """x: [N, 3] in [-1, 1] -> flat cell index [N] (clamped to the grid)."""
        r = self.cfg.resolution
        ijk = ((x + 1) * (0.5 * r)).to(torch.int64).clamp_(0, r - 1)
        return (ijk[:, 0] * r + ijk[:, 1]) * r + ijk[:, 2]

    def is_occupied(self, x: Tensor) -> Tensor:
        """x: [N, 3] -> bool [N]."""
        return self.occupied[self.cell_index(x)]

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())

    # --- updates -------------------------------------------------------------------------
    @torch.no_grad()
    def maybe_update(
        self, step: int, density_fn: Callable[[Tensor], Tensor], generator: torch.Generator | None = None
    ) -> bool:
        """Update on the schedule; returns whether it ran. density_fn: x [N, 3] in [-1, 1] -> [N]."""
        if step % self.cfg.update_every != 0:
            return False
        self.update(step, density_fn, generator)
        return True

    @torch.no_grad()
    def update(self, step: int, density_fn: Callable[[Tensor], Tensor], generator: torch.Generator | None = None) -> None:
        cells = self.cfg.resolution**3
        if step < self.cfg.warmup_steps:
            index = torch.arange(cells, device=self.device)
        else:
            judged = (self.open_until > step - self.cfg.update_every).nonzero().squeeze(-1)  # held, or just let go
            uniform = torch.randint(0, cells, (cells // 4,), generator=generator, device=self.device)
            occupied = self.occupied.nonzero().squeeze(-1)
            if occupied.numel():
                pick = torch.randint(0, occupied.numel(), (max(occupied.numel() // 4, 1),), generator=generator,
                                     device=self.device)
                index = torch.cat([uniform, occupied[pick], judged])
            else:
                index = torch.cat([uniform, judged])
        jitter = torch.rand(index.numel(), 3, generator=generator, device=self.device)
        x = (self._cell_xyz[index].float() + jitter) * (2.0 / self.cfg.resolution) - 1  # [N, 3]
        sigma = torch.cat([density_fn(chunk) for chunk in x.split(65536)])
        self.density[index] = torch.maximum(self.density[index] * self.cfg.decay, sigma)
        held = self.open_until > step  # opened for a new camera: not judged yet, not in the mean
        seen = (self.density >= 0) & ~held
        mean = self.density[seen].mean() if seen.any() else torch.tensor(0.0)
        threshold = min(float(mean), self.cfg.density_threshold)
        occupied = self.density > threshold
        if not bool(occupied.any()):
            # A uniform field has no cell above its own mean (float round-off decides): keep its
            # densest cells rather than prune everything, which no gradient could ever undo.
            occupied = self.density >= self.density.max()
        self.occupied = occupied | held

    @torch.no_grad()
    def open_frustum(self, c2w_box: Tensor, intrinsics: Tensor, width: int, height: int, unbounded: bool,
                     step: int = 0, mark_only: bool = False) -> int:
        """Open the cells a new camera is the first to see (``c2w_box`` [4, 4] in box coordinates,
        OpenGL; ``intrinsics`` [4]); returns how many were closed before.

        A keyframe that arrives while the robot trains may look at space the grid pruned because no
        keyframe had trained it yet: marching would skip it and the field could never learn it.
        Only cells no earlier camera saw are opened (re-opening what the field has trained kept the
        whole grid open in a room, where every camera sees most of it). They are held open for
        ``warmup_steps`` steps from ``step``, the new camera's own warm-up, out of the mean that sets
        the threshold, and their running max starts again from the field's density there. (Opened
        instead with a forced density just above the threshold, they raised the mean until it
        pruned the field's own faint cells and then held themselves open: streamed training stalled
        near 10 dB where offline reached 20, benchmarks/bench_stream.py --sampling.)
        ``mark_only``: only remember the cells as seen (the first keyframes, before the warm-up)."""
        r = self.cfg.resolution
        x = (self._cell_xyz.float() + 0.5) * (2.0 / r) - 1  # [C, 3] grid coordinates
        if unbounded:  # the inverse of agent.nerf.contraction.contract
            u = 2 * x
            n = u.abs().amax(-1, keepdim=True).clamp(max=1.999)
            x = torch.where(n > 1, u / n / (2 - n), u)
        w2c = torch.linalg.inv(c2w_box.to(self.device).float())
        p = x @ w2c[:3, :3].T + w2c[:3, 3]  # [C, 3] camera coordinates, looking down -z
        depth = -p[:, 2]
        fx, fy, cx, cy = [float(v) for v in intrinsics]
        safe = depth.clamp(min=1e-6)
        col, row = cx + fx * p[:, 0] / safe, cy - fy * p[:, 1] / safe
        in_view = (depth > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        new, self.seen = in_view & ~self.seen, self.seen | in_view
        if mark_only:
            return 0
        opened = int((new & ~self.occupied).sum())
        self.density[new] = -1.0  # never judged: the next update takes the field's density as it is
        self.open_until[new] = step + self.cfg.warmup_steps
        self.occupied |= new
        return opened

    # --- persistence (checkpoints) -------------------------------------------------------
    def state_dict(self) -> dict[str, Tensor]:
        return {"density": self.density.clone(), "occupied": self.occupied.clone()}

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        if state["density"].shape != self.density.shape:
            raise ValueError("occupancy grid resolution mismatch")
        self.density = state["density"].to(self.device)
        self.occupied = state["occupied"].to(self.device)
