"""Masks for every format, composited as alpha: mask_path, masks*/ folders, soft edges, all or none."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agent.data.loaders import load_views
from agent.data.views import DataError

from .helpers import colmap_dataset, pose, random_rgba, write_json, write_png

H, W = 12, 16


def soft_mask(seed: int, h: int = H, w: int = W) -> np.ndarray:
    """[h, w] grey levels in [0, 1] on the 8-bit grid, so that a PNG stores them exactly."""
    return np.round(np.random.default_rng(100 + seed).uniform(0, 1, (h, w)) * 255) / 255


def grey(m: np.ndarray) -> np.ndarray:
    return np.repeat(m[:, :, None], 3, axis=2)


def nerfstudio(root, n: int = 3, alpha: bool = False, mask_path: bool = False) -> list[np.ndarray]:
    """n frames in images/, their masks at masks/frame_i.png (named per frame with ``mask_path``)."""
    frames, images = [], []
    for i in range(n):
        img = random_rgba(H, W, i) if alpha else random_rgba(H, W, i)[..., :3]
        write_png(root / "images" / f"frame_{i}.png", img)
        images.append(np.round(img * 255) / 255)
        write_png(root / "masks" / f"frame_{i}.png", grey(soft_mask(i)))
        frame = {"file_path": f"images/frame_{i}.png", "transform_matrix": pose(10 * i, (0, 0, 3))}
        if mask_path:
            frame["mask_path"] = f"masks/frame_{i}.png"
        frames.append(frame)
    write_json(root / "transforms.json", {"camera_model": "PINHOLE", "fl_x": 20.0, "fl_y": 20.0, "frames": frames})
    return images


@pytest.mark.parametrize("mask_path", [True, False])
def test_soft_masks_become_alpha(tmp_path, mask_path):
    images = nerfstudio(tmp_path, mask_path=mask_path)
    v = load_views(tmp_path)
    assert v.images.shape == (3, H, W, 4)
    for i in range(3):
        assert np.abs(v.images[i, ..., 3].numpy() - soft_mask(i)).max() < 1e-6
        assert np.abs(v.images[i, ..., :3].numpy() - images[i]).max() < 1e-6, "colour untouched"
    assert v.meta["masks"]["count"] == 3 and v.meta["masks"]["from"] == ("mask_path" if mask_path else "folder")


def test_an_image_with_alpha_gets_alpha_times_mask(tmp_path):
    images = nerfstudio(tmp_path, alpha=True)
    v = load_views(tmp_path)
    assert np.abs(v.images[1, ..., 3].numpy() - images[1][..., 3] * soft_mask(1)).max() < 1e-6


def test_masks_are_resized_with_the_images(tmp_path):
    nerfstudio(tmp_path)
    for i in range(3):  # masks at twice the images' size: resized to the image, then with it
        big = cv2.resize(soft_mask(i), (2 * W, 2 * H), interpolation=cv2.INTER_NEAREST)
        write_png(tmp_path / "masks" / f"frame_{i}.png", grey(big))
    full = load_views(tmp_path)
    assert np.abs(full.images[0, ..., 3].numpy() - soft_mask(0)).max() < 1e-6
    half = load_views(tmp_path, width=W // 2)
    expected = cv2.resize(soft_mask(0).astype(np.float32), (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    assert np.abs(half.images[0, ..., 3].numpy() - expected).max() < 1e-5
    write_png(tmp_path / "masks" / "frame_2.png", grey(soft_mask(2, h=H, w=H)))
    with pytest.raises(DataError, match="mask is 12x12, its image 16x12: not the same aspect ratio"):
        load_views(tmp_path)


def test_masks_for_only_some_images_are_an_error_naming_the_first(tmp_path):
    nerfstudio(tmp_path, n=4)
    (tmp_path / "masks" / "frame_1.png").unlink()
    (tmp_path / "masks" / "frame_3.png").unlink()
    with pytest.raises(DataError, match=r"no mask for frame_1.png \(looked in .*masks for frame_1, frame_1_mask "
                                        r"or frame_1.png .*\); 2 of 4 images have one"):
        load_views(tmp_path)


def test_mask_path_for_only_some_frames_is_an_error(tmp_path):
    nerfstudio(tmp_path, mask_path=True)
    top = __import__("json").loads((tmp_path / "transforms.json").read_text())
    del top["frames"][2]["mask_path"]
    top["frames"][0]["mask_path"] = "masks/nope.png"
    write_json(tmp_path / "transforms.json", top)
    with pytest.raises(DataError, match=r"frame 0 \(images/frame_0.png\): mask not found: .*nope.png"):
        load_views(tmp_path)
    top["frames"][0]["mask_path"] = "masks/frame_0.png"
    write_json(tmp_path / "transforms.json", top)
    with pytest.raises(DataError, match=r"frame 2 \(images/frame_2.png\) has no mask_path while others have one"):
        load_views(tmp_path)


def test_mask_names_with_suffix_and_other_extensions(tmp_path):
    nerfstudio(tmp_path, n=2)
    (tmp_path / "masks" / "frame_0.png").rename(tmp_path / "masks" / "frame_0_mask.PNG")
    m1 = (soft_mask(1) > 0.5).astype(np.float64)  # hard, so that JPEG keeps it to within a few levels
    (tmp_path / "masks" / "frame_1.png").unlink()
    assert cv2.imwrite(str(tmp_path / "masks" / "frame_1.jpg"), np.round(m1 * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 100])
    v = load_views(tmp_path)
    assert np.abs(v.images[0, ..., 3].numpy() - soft_mask(0)).max() < 1e-6
    assert np.abs(v.images[1, ..., 3].numpy() - m1).mean() < 0.05


def test_colmap_masks_in_colmaps_own_naming(tmp_path):
    colmap_dataset(tmp_path)  # images/img0.png, img1.png at 40 x 30
    for i in range(2):
        write_png(tmp_path / "masks" / f"img{i}.png.png", grey(soft_mask(i, 30, 40)))  # COLMAP: <image name>.png
    v = load_views(tmp_path)
    assert v.images.shape == (2, 30, 40, 4) and v.meta["masks"]["count"] == 2
    assert np.abs(v.images[1, ..., 3].numpy() - soft_mask(1, 30, 40)).max() < 1e-6
    (tmp_path / "masks" / "img0.png.png").unlink()
    with pytest.raises(DataError, match=r"no mask for img0.png .*1 of 2 images have one"):
        load_views(tmp_path)
