"""Which robot holds which view: sectors of azimuth and the margin that gives the overlap asked for."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from agent.data.capture import azimuths_deg, mean_up, scene_center
from agent.data.split.config import SplitConfig
from agent.data.views import Views

__all__ = ["Sectors", "sectors", "membership", "overlaps"]


def membership(az: np.ndarray, starts: np.ndarray, width: float, delta: float) -> np.ndarray:
    """[M, N] bool: azimuth in sector k widened by delta on both sides."""
    rel = (az[:, None] - starts[None, :] + delta) % 360.0
    return rel < width + 2 * delta


def overlaps(mem: np.ndarray) -> np.ndarray:
    """[N] fraction of each robot's views that another robot also holds (nan for an empty robot)."""
    shared = mem.sum(1) > 1
    count = mem.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (mem & shared[:, None]).sum(0) / count, np.nan)


def _choose_margin(az: np.ndarray, starts: np.ndarray, width: float, target: float) -> float:
    """The margin delta in [0, w/2) whose mean achieved overlap is closest to ``target``."""
    if len(starts) < 2 or target <= 0.0:
        return 0.0
    # membership only changes where a view crosses a sector boundary: try just past each crossing
    dist = np.abs(((az[:, None] - starts[None, :] + 180.0) % 360.0) - 180.0).ravel()
    cands = np.unique(np.concatenate([[0.0], dist + 1e-6]))
    cands = cands[cands < width / 2]
    best, best_err = 0.0, math.inf
    for delta in cands:
        err = abs(float(np.nanmean(overlaps(membership(az, starts, width, delta)))) - target)
        if err < best_err - 1e-12:
            best, best_err = float(delta), err
    return best


@dataclass
class Sectors:
    center: Tensor  # [3]
    up: Tensor  # [3] unit
    azimuth_deg: Tensor  # [M] of every source view
    starts: np.ndarray  # [N] core sector starts, degrees
    width: float  # of a core sector, degrees
    margin: float  # delta, degrees


def sectors(views: Views, cfg: SplitConfig, train_idx: list[int], n: int) -> Sectors:
    """The robots' sectors about the up axis, widened by the margin that gives the requested overlap."""
    up = torch.tensor(cfg.up, dtype=torch.float64) if cfg.up is not None else mean_up(views.c2w)
    up = up / up.norm()
    center = torch.tensor(cfg.center, dtype=torch.float64) if cfg.center is not None else scene_center(views.c2w)
    az_all = azimuths_deg(views.c2w, center, up)
    width = 360.0 / n
    starts = (cfg.sector_start_deg + width * np.arange(n)) % 360.0
    delta = _choose_margin(az_all.numpy()[train_idx], starts, width, cfg.overlap)
    return Sectors(center, up, az_all, starts, width, delta)

