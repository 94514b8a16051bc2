"""Which robot holds which view: sectors of azimuth or segments of the trajectory, and the margin
that gives the overlap asked for (definitions in :mod:`agent.data.split`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from agent.camera import optical_axis
from agent.data.capture import azimuths_deg, mean_up, scene_center
from agent.data.split.config import SplitConfig
from agent.data.views import Views

__all__ = ["Assignment", "assign", "membership", "overlaps", "largest_gap"]


@dataclass
class Assignment:
    """Who holds which view, and the layout that decided it."""

    layout: str  # "circle" | "arc" (sectors of azimuth) | "trajectory" (segments of the capture order)
    center: Tensor  # [3] scene centre of the azimuths
    up: Tensor  # [3] unit up axis
    azimuth_deg: Tensor  # [M] of every source view
    train: np.ndarray  # [M_train, N] bool: robot k holds training view j
    test: np.ndarray  # [M_test, N] bool: robot k has seen test view j (its seen_by)
    ranges_deg: list[tuple[float, float]]  # [N] widened sectors, or the azimuths each segment spans
    margin_deg: float = 0.0  # sectors: delta
    margin_views: int = 0  # trajectory: views shared at each border between segments
    notes: list[str] = field(default_factory=list)


def assign(views: Views, cfg: SplitConfig, train_idx: list[int], test_idx: list[int], n: int) -> Assignment:
    """Assign the training views ``train_idx`` (and, as seen_by, the test views) to ``n`` robots."""
    up = torch.tensor(cfg.up, dtype=torch.float64) if cfg.up is not None else mean_up(views.c2w)
    up = up / up.norm()
    center = torch.tensor(cfg.center, dtype=torch.float64) if cfg.center is not None else scene_center(views.c2w)
    az_all = azimuths_deg(views.c2w, center, up)
    az = az_all.numpy()
    if cfg.by == "trajectory":
        got = _by_trajectory(views, cfg, train_idx, test_idx, n, center, up, az_all)
    else:
        layout, starts, widths = _sector_layout(az[train_idx], cfg.sector_start_deg, n)
        delta = _choose_margin(az[train_idx], starts, widths, cfg.overlap)
        ranges = [(float(s - delta), float(s + w + delta)) for s, w in zip(starts, widths)]
        got = Assignment(layout, center, up, az_all, membership(az[train_idx], starts, widths, delta),
                         membership(az[test_idx], starts, widths, delta), ranges, margin_deg=delta)
    if got.layout == "arc":
        got.notes.append(f"the training cameras cover an arc of {360.0 - largest_gap(az[train_idx])[0]:.0f} deg of "
                         "azimuth: sectors cut at its quantiles")
    if got.layout != "circle" and cfg.sector_start_deg != 0.0:
        got.notes.append(f"sector_start_deg ({cfg.sector_start_deg}) ignored: it places sectors round a full circle")
    return got


# --------------------------------------------------------------------------------------------
# Sectors
# --------------------------------------------------------------------------------------------


def largest_gap(az: np.ndarray) -> tuple[float, float]:
    """The widest empty arc between azimuths [M] (degrees): (its width, the azimuth just after it)."""
    s = np.sort(az % 360.0)
    gaps = np.diff(np.concatenate([s, s[:1] + 360.0]))
    j = int(gaps.argmax())
    return float(gaps[j]), float(s[(j + 1) % len(s)])


def _sector_layout(az: np.ndarray, start_deg: float, n: int) -> tuple[str, np.ndarray, np.ndarray]:
    """(layout, core sector starts [N], widths [N]) in degrees for the training azimuths ``az``."""
    width = 360.0 / n
    if n > 1 and largest_gap(az)[0] > width / 2:
        return ("arc", *_arc_sectors(az, n))
    return "circle", (start_deg + width * np.arange(n)) % 360.0, np.full(n, width)


def _arc_sectors(az: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Core sectors cut at the k/N quantiles of the azimuths along their arc: starts [N], widths [N].

    Each cut lies halfway between the two views it separates; the two end sectors reach halfway
    into the empty arc, so that the sectors still cover the circle (a test view there goes to
    the robot at the nearer end)."""
    gap, first = largest_gap(az)
    x = np.sort((az - first) % 360.0)  # [M] position along the arc, 0 .. 360 - gap
    cuts = [int(math.floor(k * len(x) / n + 0.5)) for k in range(1, n)]  # 1 <= cut <= M - 1 for M >= N
    edges = np.array([-gap / 2, *[(x[c - 1] + x[c]) / 2 for c in cuts], x[-1] + gap / 2])
    return (first + edges[:-1]) % 360.0, np.diff(edges)


def membership(az: np.ndarray, starts: np.ndarray, widths: np.ndarray, delta: float) -> np.ndarray:
    """[M, N] bool: azimuth in sector k (``[starts_k, starts_k + widths_k)``) widened by delta on both sides."""
    rel = (az[:, None] - starts[None, :] + delta) % 360.0
    return rel < widths[None, :] + 2 * delta


def overlaps(mem: np.ndarray) -> np.ndarray:
    """[N] fraction of each robot's views that another robot also holds (nan for an empty robot)."""
    shared = mem.sum(1) > 1
    count = mem.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (mem & shared[:, None]).sum(0) / count, np.nan)


def _choose_margin(az: np.ndarray, starts: np.ndarray, widths: np.ndarray, target: float) -> float:
    """The margin delta in [0, w/2) (w: the narrowest sector) whose mean achieved overlap is closest to ``target``."""
    if len(starts) < 2 or target <= 0.0:
        return 0.0
    # membership only changes where a view crosses a sector boundary: try just past each crossing
    dist = np.abs(((az[:, None] - starts[None, :] + 180.0) % 360.0) - 180.0).ravel()
    cands = np.unique(np.concatenate([[0.0], dist + 1e-6]))
    cands = cands[cands < widths.min() / 2]
    best, best_err = 0.0, math.inf
    for delta in cands:
        err = abs(float(np.nanmean(overlaps(membership(az, starts, widths, delta)))) - target)
        if err < best_err - 1e-12:
            best, best_err = float(delta), err
    return best


# --------------------------------------------------------------------------------------------
# Trajectory segments
# --------------------------------------------------------------------------------------------


def _segments(m: int, n: int, shared: int) -> np.ndarray:
    """[M, N] bool: robot k's positions among the M training views, when the ``shared`` views round
    each cut (``shared // 2`` before it, the rest after) belong to both neighbours."""
    cuts = np.array([int(math.floor(k * m / n + 0.5)) for k in range(n + 1)])
    pos = np.arange(m)[:, None]
    return (pos >= cuts[None, :-1] - shared // 2) & (pos < cuts[None, 1:] + (shared + 1) // 2)


def _choose_shared(m: int, n: int, target: float) -> int:
    """The views shared at each border (fewer than the shortest segment) for the closest mean overlap."""
    if n < 2 or target <= 0.0:
        return 0
    shortest = min(int(math.floor((k + 1) * m / n + 0.5)) - int(math.floor(k * m / n + 0.5)) for k in range(n))
    errors = [abs(float(np.nanmean(overlaps(_segments(m, n, s)))) - target) for s in range(shortest)]
    return int(np.argmin(errors))  # the first of equals: the fewest shared views


def _pose_distance(a: Tensor, b: Tensor, scale: float) -> Tensor:
    """[A, B]: distance of camera centres plus the angle between optical axes, weighed as the arc it
    sweeps at ``scale`` (the capture's distance to the scene).  a: [A, 4, 4], b: [B, 4, 4]."""
    da, db = optical_axis(a.double()), optical_axis(b.double())
    da, db = da / da.norm(dim=-1, keepdim=True), db / db.norm(dim=-1, keepdim=True)
    angle = torch.arccos((da @ db.T).clamp(-1.0, 1.0))
    return torch.cdist(a[:, :3, 3].double(), b[:, :3, 3].double()) + scale * angle


def _by_trajectory(views: Views, cfg: SplitConfig, train_idx: list[int], test_idx: list[int], n: int,
                   center: Tensor, up: Tensor, az_all: Tensor) -> Assignment:
    """Contiguous segments of the training views in capture order; a test view is seen by the
    robots that hold the training view nearest to it in pose."""
    m = len(train_idx)
    shared = _choose_shared(m, n, cfg.overlap)
    train = _segments(m, n, shared)
    test = np.zeros((len(test_idx), n), dtype=bool)
    if test_idx:
        cams = views.c2w.double()
        scale = float((cams[train_idx, :3, 3] - center).norm(dim=-1).median())
        nearest = _pose_distance(cams[test_idx], cams[train_idx], scale).argmin(1).numpy()
        test = train[nearest]
    az = az_all.numpy()[train_idx]
    ranges = []
    for k in range(n):
        gap, first = largest_gap(az[train[:, k]])
        ranges.append((first, first + 360.0 - gap))
    return Assignment("trajectory", center, up, az_all, train, test, ranges, margin_views=shared)
