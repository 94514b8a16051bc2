"""Regularisers on the samples of a rendered batch (the photometric loss lives in the trainer).

**Distortion** (mip-NeRF 360, as nerfacto uses it for unbounded scenes): a few views on a short
arc can be explained by semi-transparent "floaters" in the empty space in front of the walls,
each view's colours painted at a different depth. Those fit the training views and break every
other one, and two robots grow different floaters, which consensus must then undo. The loss
pulls each ray's weights into one compact interval:

    L = sum_{i,j} w_i w_j |s_i - s_j| + 1/3 sum_i w_i^2 ds_i

over the samples of a ray, in a normalised distance ``s = t / (1 + t)`` (t in box units: linear
near the camera, all of the far room within [1/2, 1)). The double sum is linear in the samples
with the exclusive cumulative sums of ``w`` and ``w s`` along the (sorted) ray.
"""

from __future__ import annotations

from torch import Tensor

from agent.nerf.sampler import Samples, exclusive_segment_cumsum


def distortion_loss(weights: Tensor, samples: Samples) -> Tensor:
    """Mean over rays of mip-NeRF 360's distortion.  weights: [S] (same order as ``samples``) -> []."""
    if len(samples) == 0:
        return weights.sum() * 0
    s = samples.t_mid / (1 + samples.t_mid)  # [S]
    ds = samples.dt / (1 + samples.t_mid) ** 2  # [S] the interval's width in s
    idx, r = samples.ray_index, samples.num_rays
    w_before = exclusive_segment_cumsum(weights, idx, r)  # [S] sum_{j<i} w_j
    ws_before = exclusive_segment_cumsum(weights * s, idx, r)  # [S] sum_{j<i} w_j s_j
    pairs = 2 * weights * (s * w_before - ws_before)  # [S]: sum over j<i of w_i w_j (s_i - s_j), both orders
    return (pairs.sum() + (weights**2 * ds).sum() / 3) / r
