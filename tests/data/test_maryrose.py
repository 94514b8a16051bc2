"""The real maryrose capture (LLFF, soft masks) from the shared data: its cameras checked by geometry.

69 photographs of a tankard on a turntable: every optical axis must pass near one point, which
every camera sees inside the object's mask; the masks must carve one consistent visual hull (a
wrong camera convention, e.g. LLFF's axes taken as they are, a 90 deg roll, does not); and the
scene box from the near/far bounds must hold that hull and every ray through the object.
Photographs CC BY 4.0: Access and Photography: Rob Kaleta; Model-build: Hugh Fiske;
Photo-masks: MicroPasts volunteers.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from agent.camera import camera_directions, optical_axis, project_points
from agent.data.capture import estimate_scene_box, scene_center
from agent.data.loaders import load_views

from .helpers import MARYROSE

pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(not MARYROSE.is_dir(), reason=f"shared data not available: {MARYROSE} is absent "
                       "(set DINERF_SHARED_DATA to the shared data folder)"),
]


@pytest.fixture(scope="module")
def maryrose():
    return load_views(MARYROSE, width=128)


def test_maryrose_loads_at_width_128_with_its_masks(maryrose):
    v = maryrose
    assert len(v) == 69 and v.images.shape == (69, 128, 128, 4) and v.meta["format"] == "llff"
    assert v.meta["images_dir"].endswith("images_4") and v.meta["masks"]["count"] == 69
    assert v.intrinsics[0].tolist() == pytest.approx([10547.2437 * 128 / 3456] * 2 + [64.0, 64.0], rel=1e-5)
    alpha = v.images[..., 3]
    assert 0.3 < float(alpha.mean()) < 0.6 and float(alpha.min()) == 0.0 and float(alpha.max()) == 1.0
    assert bool(((alpha > 0.02) & (alpha < 0.98)).any()), "soft mask edges are kept"


def test_the_optical_axes_meet_at_the_object(maryrose):
    c2w = maryrose.c2w.double()
    centre = scene_center(c2w)
    o, d = c2w[:, :3, 3], optical_axis(c2w)
    to_c = centre - o
    dist = to_c.norm(dim=-1)
    miss = (to_c - (to_c * d).sum(-1, keepdim=True) * d).norm(dim=-1)  # distance of each axis from the centre
    angle = torch.rad2deg(torch.acos((to_c * d).sum(-1) / dist))
    half_fov = math.degrees(math.atan(64 / float(maryrose.intrinsics[0, 0])))
    print(f"axes miss the centre by median {float(miss.median()):.3f}, max {float(miss.max()):.3f} "
          f"(cameras {float(dist.min()):.2f}-{float(dist.max()):.2f} away); angle to it median "
          f"{float(angle.median()):.2f}, max {float(angle.max()):.2f} deg (half fov {half_fov:.1f})")
    assert float((miss / dist).max()) < 0.06 and float(angle.max()) < 0.4 * half_fov
    uv, z = project_points(c2w, maryrose.intrinsics.double(), centre.expand(len(c2w), 3))
    assert bool((z > 0).all()), "every camera looks towards the centre"
    alpha = maryrose.images[torch.arange(len(c2w)), uv[:, 1].long(), uv[:, 0].long(), 3]
    assert float(alpha.min()) > 0.99, "and sees the object there"


def _visual_hull(c2w, k, alpha, centre, half, n=40, low=32):
    """Voxel centres [N, 3] inside every mask, and per view the IoU [M] of their silhouette with the mask at low px."""
    m_views, h, w = alpha.shape
    ax = (torch.arange(n, dtype=torch.float64) + 0.5) / n * 2 - 1
    grid = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) * half + centre
    keep = torch.ones(len(grid), dtype=torch.bool)
    uvs = []
    for m in range(m_views):
        uv, z = project_points(c2w[m].expand(len(grid), 4, 4), k[m].expand(len(grid), 4), grid)
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0)
        hit = torch.zeros(len(grid), dtype=torch.bool)
        hit[inside] = alpha[m, v[inside], u[inside]] > 0.5
        keep &= hit
        uvs.append(uv)
    masks = F.avg_pool2d(alpha[:, None].float(), w // low)[:, 0] > 0.5
    ious = []
    for m in range(m_views):
        uv = uvs[m][keep]
        sil = torch.zeros(low, low, dtype=torch.bool)
        sil[(uv[:, 1] * low / h).long().clamp(0, low - 1), (uv[:, 0] * low / w).long().clamp(0, low - 1)] = True
        ious.append(float((sil & masks[m]).sum() / (sil | masks[m]).sum().clamp(min=1)))
    return grid[keep], torch.tensor(ious)


def test_the_masks_carve_one_hull_inside_the_box(maryrose):
    c2w, k, alpha = maryrose.c2w.double(), maryrose.intrinsics.double(), maryrose.images[..., 3]
    centre, half, source = estimate_scene_box(maryrose)
    assert source == "bounds"
    hull, iou = _visual_hull(c2w, k, alpha, centre, half)
    rolled = c2w.clone()  # LLFF's [down, right, back] read as [right, up, back]: a 90 deg roll
    rolled[:, :3, 0], rolled[:, :3, 1] = -c2w[:, :3, 1], c2w[:, :3, 0]
    _, iou_rolled = _visual_hull(rolled, k, alpha, centre, half)
    extent = (hull - centre).abs().max(0).values
    print(f"visual hull: {len(hull)} voxels, silhouette IoU median {float(iou.median()):.3f} min {float(iou.min()):.3f} "
          f"(rolled cameras: median {float(iou_rolled.median()):.3f}); hull reaches {extent.tolist()} from the box "
          f"centre, box half-size {half:.3f}")
    assert float(iou.min()) > 0.7 and float(iou_rolled.median()) < 0.5
    assert float(extent.max()) < half - 2 * half / 40, "the hull stays clear of the box's faces: nothing clipped"

    misses = total = 0  # every ray through the object crosses the box
    rows, cols = torch.meshgrid(torch.arange(128) + 0.5, torch.arange(128) + 0.5, indexing="ij")
    for m in range(len(c2w)):
        sel = alpha[m] > 0.05
        d = camera_directions(k[m], cols[sel].double(), rows[sel].double()) @ c2w[m, :3, :3].T
        t1, t2 = (centre - half - c2w[m, :3, 3]) / d, (centre + half - c2w[m, :3, 3]) / d
        misses += int((torch.minimum(t1, t2).max(-1).values > torch.maximum(t1, t2).min(-1).values).sum())
        total += int(sel.sum())
    assert misses == 0, f"{misses} of {total} object pixels see past the box"
