"""LLFF folders (poses_bounds.npy + images/ and images_N/): written from known OpenGL cameras, read back exactly."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from agent.camera import project_points
from agent.data.capture import CAMERA_BOX_MARGIN, estimate_scene_box
from agent.data.loaders import load_views
from agent.data.views import DataError

from .helpers import random_rgba, write_png

W0, H0, FOCAL = 80, 60, 70.0  # the "original" size the poses' focal length belongs to


def look_at(centre: np.ndarray, target=np.zeros(3), up=np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenGL camera-to-world [4, 4] at ``centre`` looking at ``target``."""
    back = centre - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
    m[:3, 3] = centre
    return m


def ring(n: int = 5, radius: float = 4.0) -> np.ndarray:
    """[n, 4, 4] cameras round the origin at several elevations, looking at it."""
    az = np.linspace(0, 2 * np.pi, n, endpoint=False)
    el = np.linspace(-0.4, 0.6, n)
    return np.stack([look_at(radius * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]))
                     for a, e in zip(az, el)])


def write_llff(root, c2w: np.ndarray, bounds: np.ndarray, folders=(("images", 1), ("images_2", 2), ("images_4", 4))):
    """poses_bounds.npy from OpenGL cameras (LLFF columns [down, right, back] = [-up, right, back]) and images."""
    rows = []
    for m, (near, far) in zip(c2w, bounds):
        mat = np.stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3], [H0, W0, FOCAL]], 1)  # [3, 5]
        rows.append(np.concatenate([mat.ravel(), [near, far]]))
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", np.array(rows))
    images = {}
    for name, factor in folders:
        for i in range(len(c2w)):
            img = random_rgba(H0 // factor, W0 // factor, 10 * factor + i)[..., :3]
            write_png(root / name / f"IMG_{i:02d}.png", img)
            images[(name, i)] = np.round(img * 255) / 255
    return images


def test_poses_intrinsics_and_images_come_back_exactly(tmp_path):
    c2w = ring()
    bounds = np.stack([np.linspace(2.5, 3.0, 5), np.linspace(5.0, 5.5, 5)], 1)
    images = write_llff(tmp_path, c2w, bounds)
    v = load_views(tmp_path)  # the largest folder, at its size
    assert v.meta["format"] == "llff" and v.meta["images_dir"].endswith("images") and v.names[0] == "IMG_00"
    assert torch.allclose(v.c2w.double(), torch.from_numpy(c2w), atol=1e-6)
    assert v.intrinsics[0].tolist() == pytest.approx([FOCAL, FOCAL, W0 / 2, H0 / 2])
    assert np.abs(v.images[3].numpy() - images[("images", 3)]).max() < 1e-6
    assert v.meta["bounds"]["IMG_02"] == pytest.approx(bounds[2].tolist())
    assert v.meta["near_far"] == pytest.approx([2.5, 5.5]) and v.meta["original_size"] == [W0, H0]

    # a world point projects where the LLFF convention says: u = cx + f r / -b, v = cy + f d / -b
    point = np.array([0.3, -0.2, 0.1])
    for i in range(5):
        down, right, back = -c2w[i, :3, 1], c2w[i, :3, 0], c2w[i, :3, 2]
        rel = point - c2w[i, :3, 3]
        depth = -(rel @ back)
        llff_uv = np.array([W0 / 2 + FOCAL * (rel @ right) / depth, H0 / 2 + FOCAL * (rel @ down) / depth])
        uv, z = project_points(v.c2w[i:i + 1].double(), v.intrinsics[i:i + 1].double(), torch.from_numpy(point)[None])
        assert np.allclose(uv[0].numpy(), llff_uv, atol=1e-4) and float(z[0]) == pytest.approx(depth, rel=1e-6)


@pytest.mark.parametrize("width, folder, size", [
    (40, "images_2", (40, 30)),  # exactly one folder's width
    (30, "images_2", (30, 22)),  # the smallest folder at least that wide, downscaled
    (15, "images_4", (15, 11)),
    (20, "images_4", (20, 15)),
    (64, "images", (64, 48)),
])
def test_the_image_folder_follows_the_width(tmp_path, width, folder, size):
    write_llff(tmp_path, ring(), np.tile([2.5, 5.5], (5, 1)))
    v = load_views(tmp_path, width=width)
    assert v.meta["images_dir"].endswith(folder) and (v.width, v.height) == size
    sx, sy = size[0] / W0, size[1] / H0
    assert v.intrinsics[0].tolist() == pytest.approx([FOCAL * sx, FOCAL * sy, size[0] / 2, size[1] / 2])


def test_only_downscaled_folders_and_a_width_beyond_them(tmp_path):
    write_llff(tmp_path, ring(), np.tile([2.5, 5.5], (5, 1)), folders=(("images_4", 4), ("images_2", 2)))
    v = load_views(tmp_path / "poses_bounds.npy")  # the file itself will do
    assert v.meta["images_dir"].endswith("images_2") and v.width == 40  # the largest there is
    assert v.intrinsics[0, 0] == pytest.approx(FOCAL / 2)
    with pytest.raises(DataError, match="only downscaling"):
        load_views(tmp_path, width=60)


def test_masks_beside_the_images_become_alpha(tmp_path):
    write_llff(tmp_path, ring(), np.tile([2.5, 5.5], (5, 1)), folders=(("images_2", 2),))
    masks = []
    for i in range(5):
        m = np.zeros((30, 40))
        m[5 + i:20, 8:30] = 1.0
        m[4 + i, 8:30] = 0.4  # a soft edge
        masks.append(np.round(m * 255) / 255)
        write_png(tmp_path / "masks_2" / f"IMG_{i:02d}_mask.png", np.repeat(m[:, :, None], 3, 2))
    v = load_views(tmp_path)
    assert v.images.shape == (5, 30, 40, 4) and v.meta["masks"]["count"] == 5
    assert np.abs(v.images[2, ..., 3].numpy() - masks[2]).max() < 1e-6
    (tmp_path / "masks_2" / "IMG_03_mask.png").unlink()
    with pytest.raises(DataError, match=r"no mask for IMG_03.png .*masks_2.*4 of 5 images have one"):
        load_views(tmp_path)


def test_the_box_comes_from_the_bounds(tmp_path):
    write_llff(tmp_path, ring(n=8), np.tile([3.0, 5.0], (8, 1)), folders=(("images_4", 4),))
    rgb = load_views(tmp_path)
    v = dataclasses.replace(rgb, images=torch.cat([rgb.images, torch.zeros_like(rgb.images[..., :1])], -1))  # masked
    centre, half, source = estimate_scene_box(v)
    assert source == "bounds" and float(centre.norm()) < 1e-6 and half == pytest.approx(1.0)
    sub = v.subset([1, 4, 6])  # bounds are kept by name
    assert estimate_scene_box(sub)[2] == "bounds"
    # without masks the field is unbounded, and its box also holds the cameras (radius 4)
    centre, half, source = estimate_scene_box(rgb)
    reach = float(rgb.c2w[:, :3, 3].abs().amax())
    assert source == "bounds" and half == pytest.approx(reach * (1 + CAMERA_BOX_MARGIN)) and reach > 3


@pytest.mark.parametrize("edit, message", [
    (lambda a: a[:, :15], r"expected an N x 17 array"),
    (lambda a: a[:3], r"4 images but .* has 3 rows"),
    (lambda a: np.concatenate([a[:, :15] * np.r_[[2] + [1] * 14], a[:, 15:]], 1), "row 0 is not a rotation"),
    (lambda a: np.concatenate([a[:, :15], a[:, 16:17], a[:, 15:16]], 1), "row 0 has bounds near 5.5, far 2.5"),
])
def test_malformed_poses_bounds(tmp_path, edit, message):
    write_llff(tmp_path, ring(n=4), np.tile([2.5, 5.5], (4, 1)), folders=(("images_4", 4),))
    np.save(tmp_path / "poses_bounds.npy", edit(np.load(tmp_path / "poses_bounds.npy")))
    with pytest.raises(DataError, match=message):
        load_views(tmp_path)
