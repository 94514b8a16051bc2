"""Splitting into robots: sectors, overlap, held-out views, local frames, folder round trip, scene box."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from agent.camera import unproject_depth
from agent.data.folder import read_scene, read_truth
from agent.data.loaders import load_views
from agent.data.procedural import ProceduralConfig, procedural_views
from agent.data.split import (
    SplitConfig,
    azimuths_deg,
    mean_up,
    offset_transform,
    scene_center,
    split_views,
    write_split,
)
from agent.data.views import DataError, Views
from agent.geometry import (
    sim3_decompose,
    transform_c2w,
    transform_points,
)


@pytest.fixture(scope="module")
def views() -> Views:
    return procedural_views(ProceduralConfig(num_views=80, width=24, height=24, seed=0))


def _world_again(result, rid):
    rob = result.robots[rid]
    return transform_c2w(rob.T_world_from_local, rob.views.c2w.double())


def test_centre_and_up_of_an_orbit(views):
    assert torch.allclose(scene_center(views.c2w), torch.zeros(3, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(mean_up(views.c2w), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-5)
    az = azimuths_deg(views.c2w, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0]))
    c = views.c2w[:, :3, 3].double()
    expect = torch.rad2deg(torch.atan2(c[:, 1], c[:, 0])) % 360
    assert torch.allclose(az, expect, atol=1e-6)


@pytest.mark.parametrize("robots", [1, 2, 3, 5])
def test_sectors_partition_the_training_views_and_hold_out_every_kth(views, robots):
    r = split_views(views, SplitConfig(robots=robots, test_every=8))
    assert r.eval_indices == list(range(0, 80, 8))
    assigned = [i for rob in r.robots.values() for i in rob.indices]
    assert sorted(assigned) == [i for i in range(80) if i % 8], "each training view in exactly one robot"
    assert not set(assigned) & set(r.eval_indices), "held-out views are used by nobody"
    assert r.mean_overlap == 0.0 and all(len(s) == 1 for s in r.seen_by)
    assert list(r.robots) == list(range(1, robots + 1)) and r.reference_id == 1
    for rid, rob in r.robots.items():  # each robot's views lie in its sector
        a, b = rob.sector_deg
        az = r.azimuth_deg[rob.indices]
        assert bool((((az - a) % 360) < (b - a)).all())


@pytest.mark.parametrize("overlap", [0.1, 0.2, 0.4])
def test_overlap_is_achieved_and_reported(views, overlap):
    r = split_views(views, SplitConfig(robots=3, overlap=overlap))
    assert abs(r.mean_overlap - overlap) < 0.05
    for rid, rob in r.robots.items():  # recompute the definition from the indices
        others = {i for j, o in r.robots.items() if j != rid for i in o.indices}
        shared = sum(1 for i in rob.indices if i in others)
        assert rob.overlap == pytest.approx(shared / len(rob.indices))
    assert r.mean_overlap == pytest.approx(np.mean([rob.overlap for rob in r.robots.values()]))
    assert all(not set(rob.indices) & set(r.eval_indices) for rob in r.robots.values())
    # "views only other robots saw": held-out views whose seen_by excludes robot 1
    for idx, seen in zip(r.eval_indices, r.seen_by):
        az = float(r.azimuth_deg[idx])
        a, b = r.robots[1].sector_deg
        assert (1 in seen) == (((az - a) % 360) < (b - a))


@pytest.mark.parametrize("frame", ["first_camera", "offset", "world", "random"])
def test_local_poses_composed_with_the_truth_give_the_world_poses(views, frame):
    cfg = SplitConfig(robots=3, frame=frame, random_max_scale=2.0, depth_prior="true", seed=3)
    r = split_views(views, cfg)
    for rid, rob in r.robots.items():
        assert torch.allclose(_world_again(r, rid), views.c2w[rob.indices].double(), atol=1e-4)
        s = float(sim3_decompose(rob.T_world_from_local)[0])
        assert torch.allclose(rob.views.depth * s, views.depth[rob.indices], atol=1e-4), "depth divided by the scale"
        if frame == "first_camera":
            assert torch.allclose(rob.views.c2w[0], torch.eye(4), atol=1e-5)
        if frame == "world":
            assert torch.equal(rob.T_world_from_local, torch.eye(4, dtype=torch.float64))
        if frame == "offset":
            expect = torch.eye(4, dtype=torch.float64) if rid == 1 else offset_transform((30, 30, 30), (3, 3, 3))
            assert torch.allclose(rob.T_world_from_local, expect)
    scales = [float(sim3_decompose(rob.T_world_from_local)[0]) for rob in r.robots.values()]
    if frame == "random":
        assert max(abs(s - 1) for s in scales) > 1e-3 and all(0.5 <= s <= 2.0 for s in scales)
    else:
        assert all(abs(s - 1) < 1e-5 for s in scales)


def test_offset_rotation_is_30_degrees_about_each_axis():
    t = offset_transform((30, 30, 30), (3, 3, 3))
    a = np.radians(30)
    c, s = np.cos(a), np.sin(a)
    rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    assert np.allclose(t[:3, :3].numpy(), rz @ ry @ rx) and t[:3, 3].tolist() == [3, 3, 3]


def test_scaled_depth_prior(views):
    r = split_views(views, SplitConfig(robots=2, depth_prior="scaled", seed=1))
    for rid, rob in r.robots.items():
        a, b = rob.depth_affine[:, 0], rob.depth_affine[:, 1]
        assert bool(((a >= 0.5) & (a <= 2.0) & (b >= -0.5) & (b <= 0.5)).all())
        true = views.depth[rob.indices].double()
        known = true > 0
        expect = torch.where(known, a[:, None, None] * true + b[:, None, None], 0.0)
        assert torch.allclose(rob.views.depth.double(), expect, atol=1e-4)
        assert torch.equal(rob.views.depth > 0, known)


def test_round_trip_through_the_folder_format(views, tmp_path):
    cfg = SplitConfig(robots=2, overlap=0.2, frame="random", random_max_scale=1.5, depth_prior="scaled", seed=5)
    r = split_views(views, cfg)
    write_split(r, tmp_path)
    for rid, rob in r.robots.items():
        back = load_views(tmp_path / f"robot{rid}")
        assert back.names == rob.views.names
        assert torch.allclose(back.c2w, rob.views.c2w, atol=1e-6)
        assert torch.allclose(back.intrinsics, rob.views.intrinsics)
        assert (back.images - rob.views.images).abs().max() <= 0.5 / 255 + 1e-6, "8-bit PNG quantisation only"
        assert torch.equal(back.depth, rob.views.depth)
        spec = json.loads((tmp_path / f"robot{rid}/transforms.json").read_text())
        assert {"w", "h", "fl_x", "fl_y", "cx", "cy", "frames"} <= set(spec)
        assert "T_world_from_local" not in json.dumps(spec), "no truth in a robot folder"
    ev = load_views(tmp_path / "eval")
    assert ev.names == [views.names[i] for i in r.eval_indices]
    assert torch.allclose(ev.c2w, views.c2w[r.eval_indices], atol=1e-6), "eval views stay in the world frame"
    frames = json.loads((tmp_path / "eval/transforms.json").read_text())["frames"]
    assert [f["seen_by"] for f in frames] == r.seen_by
    truth = read_truth(tmp_path)
    assert truth["reference_id"] == 1
    for rid, rob in r.robots.items():
        t = truth["robots"][str(rid)]
        assert torch.allclose(t["T_world_from_local"], rob.T_world_from_local)
        assert len(t["depth_affine"]["per_view"]) == len(rob.indices)
    assert torch.allclose(truth["robots"]["1"]["T_shared_from_local"], torch.eye(4, dtype=torch.float64), atol=1e-12)
    split = json.loads((tmp_path / "split.json").read_text())
    assert split["mean_overlap"] == pytest.approx(r.mean_overlap)
    assert split["robots"]["2"]["views"] == r.robots[2].views.names
    with pytest.raises(DataError, match="not empty"):
        write_split(r, tmp_path)
    write_split(split_views(views, SplitConfig(robots=1)), tmp_path, overwrite=True)
    assert not (tmp_path / "robot2").exists(), "no stale robot of an earlier split"


@pytest.mark.parametrize("frame", ["first_camera", "random"])
def test_scene_box_maps_the_world_box_into_the_unit_cube(views, tmp_path, frame):
    r = split_views(views, SplitConfig(robots=3, frame=frame, random_max_scale=2.0, depth_prior="true", seed=2))
    write_split(r, tmp_path)
    scene = read_scene(tmp_path / "robot2")  # found from a robot folder too
    assert scene.reference_id == 1 and torch.allclose(scene.box_from_shared, r.box_from_shared)
    corners = torch.tensor([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float64)
    t_shared = r.T_shared_from_local
    for rid, rob in r.robots.items():
        # the world box corners as robot rid sees them, then into the box through the shared frame
        local = transform_points(torch.linalg.inv(rob.T_world_from_local), corners)
        box = transform_points(scene.box_from_shared @ t_shared[rid], local)
        assert torch.allclose(box, corners, atol=1e-6)
    # every surface point a robot sees, unprojected in its local frame, lands inside [-1, 1]^3
    for rid, rob in r.robots.items():
        v = rob.views
        for i in range(0, len(v), 5):
            local = unproject_depth(v.depth[i], v.intrinsics[i], v.c2w[i])
            box = transform_points(scene.box_from_shared @ t_shared[rid], local)
            assert float(box.abs().max()) <= 1.0 + 1e-4


def test_images_only_robots(views, tmp_path):
    r = split_views(views, SplitConfig(robots=2, images_only=True))
    write_split(r, tmp_path)
    assert not (tmp_path / "robot1/transforms.json").exists()
    assert len(list((tmp_path / "robot1/images").glob("*.png"))) == len(r.robots[1].indices)
    assert (tmp_path / "truth.json").exists()


def test_split_errors(views, tmp_path):
    with pytest.raises(DataError, match="needs a source with depth"):
        no_depth = Views(views.images[:10], views.c2w[:10], views.intrinsics[:10], views.names[:10])
        split_views(no_depth, SplitConfig(depth_prior="true"))
    with pytest.raises(DataError, match="gets no views"):
        split_views(views.subset([1, 2, 3]), SplitConfig(robots=12, test_every=0))
    with pytest.raises(DataError, match="overlap"):
        SplitConfig(overlap=0.5)
    with pytest.raises(DataError, match="frame must be one of"):
        SplitConfig(frame="nope")  # type: ignore[arg-type]


def test_sparse_sfm_depth_survives_split_and_downscaled_reload(tmp_path):
    from .helpers import colmap_dataset

    colmap_dataset(tmp_path / "src")
    src = load_views(tmp_path / "src")
    r = split_views(src, SplitConfig(robots=1, test_every=0, depth_prior="true"))
    write_split(r, tmp_path / "out")
    back = load_views(tmp_path / "out/robot1")
    assert back.meta["depth_sparse"] and torch.equal(back.depth, r.robots[1].views.depth)
    small = load_views(tmp_path / "out/robot1", width=20)
    for big, little in zip(back.depth, small.depth):  # every point lands in its pixel; only collisions merge
        rows, cols = torch.nonzero(big > 0, as_tuple=True)
        target = {(int(r) // 2, int(c) // 2) for r, c in zip(rows, cols)}
        assert {(int(r), int(c)) for r, c in zip(*torch.nonzero(little > 0, as_tuple=True))} == target
    with pytest.raises(DataError, match=r"output of `dinerf-agent split`.*robot1"):
        load_views(tmp_path / "out")
