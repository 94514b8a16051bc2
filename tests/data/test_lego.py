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


def test_the_box_from_a_robots_sfm_depth_does_not_clip_lego(tmp_path, lego):
    """An images-only robot derives the swarm's field box from its sparse SfM depth.

    A box that cuts off the model's extremities leaves them unrenderable for every robot: on a
    lego swarm the old 2nd-98th percentile box cost the robots 1-3 dB on their own views.
    """
    from agent import geometry as G
    from agent.data.sfm import SfmConfig, run_sfm

    robot = split_views(lego, SplitConfig(robots=2)).robots[1]
    folder = tmp_path / "robot"
    folder.mkdir()
    for i in robot.indices:  # the original 400 px RGBA files, as a robot with images only has them
        name = lego.names[i]
        (folder / f"{name}.png").write_bytes((LEGO / "train" / f"{name}.png").read_bytes())
    views = run_sfm(folder, width=100, config=SfmConfig(max_image_size=400))
    true_c2w = lego.c2w[[lego.names.index(n) for n in views.names]].double()
    world_from_sfm = G.umeyama(views.c2w[:, :3, 3].double(), true_c2w[:, :3, 3])

    centre, half, source = estimate_scene_box(views)
    assert source == "depth"
    points = torch.cat([G.unproject_depth(views.depth[k], views.intrinsics[k], views.c2w[k])
                        for k in range(len(views))])  # [N, 3] the sparse depth, SfM frame
    world = G.transform_points(world_from_sfm, points)
    in_true_box = (world.abs() <= 1.5).all(dim=1)  # the customary Blender box
    in_estimate = ((points - centre).abs() <= half).all(dim=1)
    clipped = float((in_true_box & ~in_estimate).sum() / in_true_box.sum())
    scale = float(torch.linalg.det(world_from_sfm[:3, :3]) ** (1 / 3))
    assert clipped < 0.003, f"the box cuts {clipped:.2%} of the scene's points"
    assert 1.2 < half * scale < 2.0, half * scale  # and it is not so large that the field's resolution is wasted
