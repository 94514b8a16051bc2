"""Image quality metrics used by every report (PSNR, SSIM), on images in [0, 1], and their mean."""

from __future__ import annotations

import math
import statistics
from typing import Iterable

import torch
import torch.nn.functional as F
from torch import Tensor


def psnr(pred: Tensor, target: Tensor) -> float:
    """pred, target: [..., 3] in [0, 1]."""
    mse = float(((pred - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred: Tensor, target: Tensor, window: int = 11, sigma: float = 1.5) -> float:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, averaged over channels.

    pred, target: [H, W, 3] in [0, 1]. Valid-region filtering as in the usual NeRF evaluation.
    """
    c1, c2 = 0.01**2, 0.03**2
    coords = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    g = (g / g.sum()).to(pred.dtype)
    kernel = (g[:, None] * g[None, :])[None, None].repeat(3, 1, 1, 1)  # [3, 1, k, k]
    x = pred.permute(2, 0, 1)[None]
    y = target.permute(2, 0, 1)[None]

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(t, kernel, groups=3)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return float(s.mean())


def finite_mean(values: Iterable[float | None]) -> float | None:
    """The mean of the values that are numbers (None and NaN skipped); None when none is."""
    xs = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return statistics.fmean(xs) if xs else None
