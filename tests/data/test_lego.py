"""The real Blender lego scene from ../shared/data: loads at width 100 with the right focal length."""

from __future__ import annotations

import math

import pytest
import torch

from agent.data.loaders import load_views
from agent.data.split import SplitConfig, estimate_scene_box, split_views

from .helpers import LEGO

pytestmark = [
    pytest.mark.data,
    pytest.mark.skipif(not LEGO.is_dir(), reason=f"shared data not available: {LEGO} is absent"),
]


@pytest.fixture(scope="module")
def lego():
    return load_views(LEGO, width=100)


def test_lego_at_width_100(lego):
    assert len(lego) == 100 and lego.images.shape == (100, 100, 100, 4)
    f = 0.5 * 100 / math.tan(0.5 * 0.6911112070083618)
    assert float(lego.intrinsics[0, 0]) == pytest.approx(f, rel=1e-6)  # ~138.89
    assert lego.intrinsics[0, 2:].tolist() == [50.0, 50.0]
    assert lego.names[:2] == ["r_0", "r_1"]
    dist = lego.c2w[:, :3, 3].norm(dim=-1)
    assert torch.allclose(dist, torch.full((100,), 4.031), atol=0.01)
    alpha = lego.images[..., 3]
    assert 0.2 < float(alpha.mean()) < 0.4 and float(alpha.min()) == 0.0


def test_lego_splits_into_two_halves(lego):
    r = split_views(lego, SplitConfig(robots=2))
    assert r.eval_indices[:3] == [0, 8, 16] and len(r.eval_indices) == 13
    assert sum(len(rob.indices) for rob in r.robots.values()) == 87
    centre, half, src = estimate_scene_box(lego)
    assert src == "cameras" and 1.3 < half < 1.6 and float(centre.norm()) < 0.05
