"""Loader conventions (Blender, nerfstudio, instant-ngp, COLMAP), downscaling, and every error case."""

from __future__ import annotations

import math
import shutil
import sys
import types

import cv2
import numpy as np
import pytest
import torch

from agent.data.images import resize_depth
from agent.data.loaders import load_views
from agent.data.views import DataError, Views

from .helpers import blender_dataset, colmap_dataset, pose, random_rgba, write_json, write_png

# ------------------------------------------------------------------------------ transforms.json


def test_blender_camera_angle_and_paths_without_extension(tmp_path):
    blender_dataset(tmp_path)
    v = load_views(tmp_path)
    assert isinstance(v, Views) and len(v) == 3
    assert v.images.shape == (3, 12, 16, 4), "RGBA must be kept as 4 channels"
    fx = 0.5 * 16 / math.tan(0.4)
    assert torch.allclose(v.intrinsics, torch.tensor([[fx, fx, 8.0, 6.0]] * 3), atol=1e-4)
    assert v.names == ["r_0", "r_1", "r_2"]
    assert torch.allclose(v.c2w[2].double(), torch.tensor(pose(60, (2, 1, 4)), dtype=torch.float64), atol=1e-6)
    img = cv2.imread(str(tmp_path / "train/r_1.png"), cv2.IMREAD_UNCHANGED)
    assert torch.allclose(v.images[1, ..., 3], torch.from_numpy(img[..., 3] / 255.0).float())
    assert torch.allclose(v.images[1, ..., 0], torch.from_numpy(img[..., 2] / 255.0).float()), "BGR must become RGB"
    assert v.meta["format"] == "blender" and v.depth is None


def test_blender_camera_angle_y_gives_fy_and_rgb_composites(tmp_path):
    blender_dataset(tmp_path, camera_angle_y=0.7)
    v = load_views(tmp_path / "transforms_train.json")
    assert float(v.intrinsics[0, 1]) == pytest.approx(0.5 * 12 / math.tan(0.35), rel=1e-6)
    white = v.rgb(1.0)
    a = v.images[..., 3:]
    assert white.shape == (3, 12, 16, 3)
    assert torch.allclose(white, v.images[..., :3] * a + (1 - a))
    assert torch.allclose(v.rgb(torch.tensor([0.0, 0.5, 1.0]))[..., 1][a[..., 0] == 0], torch.tensor(0.5))


def test_nerfstudio_per_frame_intrinsics_and_depth_files(tmp_path):
    h, w = 10, 14
    write_png(tmp_path / "images/a.png", random_rgba(h, w, 0)[..., :3])
    write_png(tmp_path / "images/b.png", random_rgba(h, w, 1)[..., :3])
    da = np.linspace(1, 3, h * w, dtype=np.float32).reshape(h, w)
    da[0, 0] = 0.0
    np.save(tmp_path / "a_depth.npy", da)
    db = np.full((h, w), 2500, dtype=np.uint16)  # millimetres
    write_png(tmp_path / "depth/b.png", db)
    frames = [
        {"file_path": "images/a.png", "fl_x": 20.0, "fl_y": 21.0, "cx": 7.5, "cy": 4.5, "w": w, "h": h,
         "transform_matrix": pose(10, (0, 0, 3)), "depth_file_path": "a_depth.npy"},
        {"file_path": "images/b.png", "fl_x": 30.0, "fl_y": 31.0, "cx": 6.5, "cy": 5.5, "w": w, "h": h,
         "transform_matrix": pose(20, (1, 0, 3)), "depth_file_path": "depth/b.png"},
    ]
    write_json(tmp_path / "transforms.json", {"camera_model": "OPENCV", "frames": frames})
    v = load_views(tmp_path)
    assert v.images.shape == (2, h, w, 3)
    assert v.intrinsics.tolist() == [[20.0, 21.0, 7.5, 4.5], [30.0, 31.0, 6.5, 5.5]]
    assert v.depth is not None and torch.allclose(v.depth[0], torch.from_numpy(da))
    assert torch.allclose(v.depth[1], torch.full((h, w), 2.5)), "16-bit PNG depth is millimetres by default"
    assert v.meta["format"] == "nerfstudio"


def test_instant_ngp_top_level_intrinsics_declared_size_and_distortion(tmp_path):
    # images on disk at half the declared size (a downscaled copy): intrinsics follow the images
    write_png(tmp_path / "img/0.png", random_rgba(8, 12, 0))
    write_png(tmp_path / "img/1.png", random_rgba(8, 12, 1)[..., :3])
    top = {"fl_x": 40.0, "fl_y": 44.0, "cx": 12.0, "cy": 7.0, "w": 24, "h": 16, "k1": 0.01, "aabb_scale": 4,
           "depth_unit_scale_factor": 0.5}
    frames = [{"file_path": f"img/{i}.png", "transform_matrix": pose(5 * i, (0, i, 2))} for i in range(2)]
    write_json(tmp_path / "transforms.json", {**top, "frames": frames})
    v = load_views(tmp_path, undistort=False)  # distortion left in the images: intrinsics as declared
    assert v.intrinsics[0].tolist() == [20.0, 22.0, 6.0, 3.5]
    assert v.images.shape[-1] == 4 and bool((v.images[1, ..., 3] == 1).all()), "RGB frames get alpha 1 beside RGBA ones"
    assert any("distortion ignored" in n for n in v.meta["notes"])
    assert any("intrinsics scaled" in n for n in v.meta["notes"])
    assert v.meta["aabb_scale"] == 4 and v.meta["format"] == "instant-ngp"


def _project(c2w: torch.Tensor, k: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """OpenGL camera: continuous pixel coordinates (u, v) of world points x: [N, 3] -> [N, 2]."""
    p = (x - c2w[:3, 3]) @ c2w[:3, :3]  # camera coordinates, -z forward
    return torch.stack([k[0] * p[:, 0] / -p[:, 2] + k[2], -k[1] * p[:, 1] / -p[:, 2] + k[3]], -1)


def test_downscale_keeps_the_projection_of_a_point_on_its_image_content(tmp_path):
    h, w = 30, 40
    img = np.zeros((h, w, 4))
    img[..., 3] = 1.0
    img[8:12, 20:24, :3] = 1.0  # a white block centred at the continuous pixel (22, 10)
    write_png(tmp_path / "images/a.png", img)
    depth = np.full((h, w), 2.0, np.float32)
    depth[:, 20:] = 5.0  # a depth edge: must never be blended
    np.save(tmp_path / "a.npy", depth)
    c2w = pose(0, (0, 0, 0))
    frames = [{"file_path": "images/a.png", "transform_matrix": c2w, "depth_file_path": "a.npy"}]
    write_json(tmp_path / "transforms.json", {"fl_x": 35.0, "fl_y": 33.0, "cx": 19.0, "cy": 16.0, "frames": frames})
    full = load_views(tmp_path)
    # the 3-D point that projects to the block centre at full resolution
    k = full.intrinsics[0].double()
    z = 3.0
    point = torch.tensor([[(22 - k[2]) / k[0] * z, -(10 - k[3]) / k[1] * z, -z]], dtype=torch.float64)
    assert torch.allclose(_project(full.c2w[0].double(), k, point), torch.tensor([[22.0, 10.0]], dtype=torch.float64))
    for width in (20, 16):  # an integer and a non-integer factor
        small = load_views(tmp_path, width=width)
        s = width / w
        assert small.width == width and small.height == round(h * s)
        uv = _project(small.c2w[0].double(), small.intrinsics[0].double(), point)[0]
        lum = small.images[0, ..., 0].double()
        rows, cols = torch.meshgrid(torch.arange(small.height) + 0.5, torch.arange(small.width) + 0.5, indexing="ij")
        centroid = torch.stack([(lum * cols).sum() / lum.sum(), (lum * rows).sum() / lum.sum()])
        assert torch.allclose(uv, torch.tensor([22 * s, 10 * s], dtype=torch.float64), atol=1e-5)
        assert torch.allclose(centroid, uv, atol=0.15), (width, centroid, uv)
        assert set(small.depth.unique().tolist()) <= {2.0, 5.0}, "depth resized without blending"


def test_sparse_depth_downscale_keeps_every_point():
    d = np.zeros((20, 20), np.float32)
    d[3, 4], d[3, 5], d[17, 18] = 2.0, 1.5, 4.0
    small = resize_depth(d, 10, 10, sparse=True)
    assert small[1, 2] == 1.5 and small[8, 9] == 4.0 and (small > 0).sum() == 2


# ------------------------------------------------------------------------------ COLMAP


def test_colmap_text_model_poses_intrinsics_and_sparse_depth(tmp_path):
    points, keypoints, (fx, fy, cx, cy) = colmap_dataset(tmp_path)
    v = load_views(tmp_path)  # finds sparse/0 and images/
    assert v.names == ["img0", "img1"] and v.images.shape == (2, 30, 40, 3)
    assert v.intrinsics[0].tolist() == pytest.approx([fx, fy, cx, cy])
    pts = torch.from_numpy(points)
    for i, (uv, z) in enumerate(keypoints):
        c2w = v.c2w[i].double()
        assert torch.allclose(c2w[:3, :3] @ c2w[:3, :3].T, torch.eye(3, dtype=torch.float64), atol=1e-6)
        # the OpenGL camera projects every 3-D point onto its COLMAP keypoint
        assert torch.allclose(_project(c2w, v.intrinsics[i].double(), pts), torch.from_numpy(uv), atol=1e-4)
        # sparse z-depth at the keypoint pixels, 0 elsewhere
        d = v.depth[i]
        for (u, vv), zz in zip(uv, z):
            assert float(d[int(vv), int(u)]) == pytest.approx(zz, rel=1e-5)
        assert int((d > 0).sum()) == len(np.unique(np.floor(uv).astype(int), axis=0))
    assert v.meta["format"] == "colmap" and v.meta["depth_sparse"]


def test_colmap_binary_model_downscaled_and_distortion_note(tmp_path):
    import pycolmap

    points, keypoints, _ = colmap_dataset(tmp_path, model="SIMPLE_RADIAL", params=(50.0, 20.0, 15.0, 0.01))
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse/0"))
    binary = tmp_path / "bin_model"
    binary.mkdir()
    rec.write_binary(str(binary))
    v = load_views(binary, width=20, images_dir=tmp_path / "images", undistort=False)
    assert v.width == 20 and v.height == 15
    assert v.intrinsics[0].tolist() == pytest.approx([25.0, 25.0, 10.0, 7.5])
    assert any("SIMPLE_RADIAL distortion ignored" in n for n in v.meta["notes"])
    uv, z = keypoints[1]
    pts = torch.from_numpy(points)
    assert torch.allclose(_project(v.c2w[1].double(), v.intrinsics[1].double(), pts), torch.from_numpy(uv) / 2, atol=1e-4)
    assert float(v.depth[1][int(uv[0, 1] / 2), int(uv[0, 0] / 2)]) == pytest.approx(z[0], rel=1e-5)


def test_colmap_unsupported_model_is_a_clear_error(tmp_path):
    colmap_dataset(tmp_path, model="OPENCV_FISHEYE", params=(50.0, 52.0, 20.5, 14.5, 0.1, 0.0, 0.0, 0.0))
    with pytest.raises(DataError, match="OPENCV_FISHEYE.*undistort"):  # a fisheye cannot be ignored
        load_views(tmp_path, undistort=False)
    shutil.rmtree(tmp_path / "sparse")
    colmap_dataset(tmp_path, model="FOV", params=(50.0, 52.0, 20.5, 14.5, 0.1))
    with pytest.raises(DataError, match="uses FOV; expected one of .*OPENCV_FISHEYE.*undistort first"):
        load_views(tmp_path)


# ------------------------------------------------------------------------------ images only, procedural


def test_images_only_without_sfm_says_so(tmp_path, monkeypatch):
    write_png(tmp_path / "a.png", random_rgba(4, 4, 0)[..., :3])
    monkeypatch.setitem(sys.modules, "agent.data.sfm", None)  # as if not installed
    with pytest.raises(DataError, match="SfM support .* not installed"):
        load_views(tmp_path)


def test_images_only_goes_to_run_sfm_when_present(tmp_path, monkeypatch):
    write_png(tmp_path / "images/a.png", random_rgba(4, 6, 0)[..., :3])
    calls = []

    def run_sfm(folder, width=None):
        calls.append((folder, width))
        return Views(torch.zeros(1, 4, 6, 3), torch.eye(4)[None], torch.tensor([[5.0, 5.0, 3.0, 2.0]]), ["a"])

    fake = types.ModuleType("agent.data.sfm")
    fake.run_sfm = run_sfm
    monkeypatch.setitem(sys.modules, "agent.data.sfm", fake)
    v = load_views(tmp_path, width=3)
    assert calls == [(tmp_path, 3)] and v.width == 3 and v.intrinsics[0].tolist() == [2.5, 2.5, 1.5, 1.0]


def test_procedural_spec_is_parsed():
    v = load_views("procedural:views=5,width=24,seed=3")
    assert len(v) == 5 and v.width == 24 and v.height == 24
    assert load_views("procedural:views=3", width=16).images.shape == (3, 16, 16, 4)
    assert load_views("procedural:views=2,width=32,height=16").images.shape == (2, 16, 32, 4)
    with pytest.raises(DataError, match="bad item 'colour=3'.*num_views"):
        load_views("procedural:colour=3")


# ------------------------------------------------------------------------------ errors


def test_missing_folder_lists_what_was_expected(tmp_path):
    with pytest.raises(DataError, match="no such file or folder; expected transforms.json, transforms_train.json, .*sparse/0"):
        load_views(tmp_path / "nope")


def test_unknown_layout_lists_what_was_expected_and_what_was_found(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DataError, match=r"no known dataset layout; expected transforms.json.*notes.txt"):
        load_views(tmp_path)


@pytest.mark.parametrize(
    "content, message",
    [
        ({"camera_angle_x": 0.8}, "no frames"),
        ({"camera_angle_x": 0.8, "frames": []}, "no frames"),
        ("[1, 2", "not valid JSON"),
        ({"frames": [{"file_path": "./train/r_0", "transform_matrix": pose(0, (0, 0, 1))}]}, "no focal length.*camera_angle_x"),
        ({"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0"}]}, "transform_matrix"),
        ({"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_9", "transform_matrix": pose(0, (0, 0, 1))}]},
         r"image not found: .*r_9"),
        ({"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]}]},
         "not invertible"),
        ({"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[float("nan")] * 4] * 4}]},
         "NaN"),
        ({"camera_angle_x": 0.8, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[1, 0], [0, 1]]}]},
         "must be 4x4"),
        ({"camera_angle_x": 0.8, "camera_model": "EQUIRECTANGULAR", "frames": [{"file_path": "a", "transform_matrix": []}]},
         "EQUIRECTANGULAR is not supported"),
    ],
)
def test_malformed_transforms_json(tmp_path, content, message):
    write_png(tmp_path / "train/r_0.png", random_rgba(4, 4, 0))
    path = tmp_path / "transforms.json"
    path.write_text(content if isinstance(content, str) else __import__("json").dumps(content))
    with pytest.raises(DataError, match=message):
        load_views(tmp_path)


def test_a_fisheye_without_undistortion_is_a_clear_error(tmp_path):
    """OPENCV_FISHEYE is undone by default (tests/data/test_undistort.py); ignoring it is refused."""
    write_png(tmp_path / "train/r_0.png", random_rgba(4, 4, 0))
    content = {"camera_angle_x": 0.8, "camera_model": "OPENCV_FISHEYE", "frames": [{"file_path": "a", "transform_matrix": []}]}
    write_json(tmp_path / "transforms.json", content)
    with pytest.raises(DataError, match="OPENCV_FISHEYE is not supported"):
        load_views(tmp_path, undistort=False)


def test_inconsistent_image_sizes_name_both_images(tmp_path):
    blender_dataset(tmp_path, n=2)
    write_png(tmp_path / "train/r_1.png", random_rgba(5, 5, 0))
    with pytest.raises(DataError, match=r"inconsistent image sizes: ./train/r_1 is 5x5 but ./train/r_0 is 16x12"):
        load_views(tmp_path)


def test_upscaling_and_missing_depth_file_are_errors(tmp_path):
    blender_dataset(tmp_path, n=1)
    with pytest.raises(DataError, match="only downscaling"):
        load_views(tmp_path, width=64)
    write_png(tmp_path / "images/a.png", random_rgba(4, 4, 0))
    write_json(tmp_path / "d/transforms.json", {"fl_x": 5.0, "frames": [
        {"file_path": "../images/a.png", "transform_matrix": pose(0, (0, 0, 1)), "depth_file_path": "missing.npy"}]})
    with pytest.raises(DataError, match="depth file not found: .*missing.npy"):
        load_views(tmp_path / "d")


def test_a_colmap_folder_with_missing_images_names_the_image(tmp_path):
    colmap_dataset(tmp_path)
    (tmp_path / "images/img1.png").unlink()
    with pytest.raises(DataError, match="img1.png"):
        load_views(tmp_path)
