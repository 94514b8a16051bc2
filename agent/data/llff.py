"""LLFF datasets: ``poses_bounds.npy`` beside ``images/`` and/or downscaled ``images_N/`` folders.

``poses_bounds.npy`` is N x 17, one row per image in sorted file-name order: a 3x5 matrix
(camera axes [down, right, back] and centre in the world, then a column H, W, focal at the
ORIGINAL image size) and the near and far depth bounds of the scene in that view. LLFF cameras
are pinholes with the principal point at the image centre. The bounds are kept in ``meta`` so
that :func:`agent.data.capture.estimate_scene_box` can carve the scene's box from them.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from agent.camera import llff_to_opengl_c2w
from agent.data.frames import load_pixels
from agent.data.images import list_image_files, read_raw, stack_images
from agent.data.masks import find_masks, masks_meta
from agent.data.views import DataError, Views
from agent.progress import track

__all__ = ["POSES_BOUNDS", "load_llff", "choose_image_dir"]

POSES_BOUNDS = "poses_bounds.npy"


def load_llff(folder: str | Path, *, width: int | None = None) -> Views:
    """Read an LLFF folder: OpenGL poses, intrinsics at the loaded size, near/far bounds in ``meta``.

    width: the images come from the smallest ``images_N/`` at least this wide (else the largest
    folder there is), then are downscaled to it; None: the largest folder, at its size.
    meta: ``bounds`` {name: [near, far]} (per view, so that subsets keep theirs), ``near_far``
    [min near, max far], ``original_size`` [W, H] of the poses' images, ``images_dir``.
    """
    folder = Path(folder)
    poses, bounds, hwf = _read_poses_bounds(folder / POSES_BOUNDS)
    img_dir, files = choose_image_dir(folder, width)
    if len(files) != len(poses):
        raise DataError(f"{img_dir}: {len(files)} images but {folder / POSES_BOUNDS} has {len(poses)} rows "
                        "(one per image, in sorted file-name order)")
    masks = find_masks(files, where=f"{folder}: ")
    pixels = []
    for i, f in enumerate(track(files, f"loading {img_dir.name}")):
        h_orig, w_orig, focal = hwf[i]

        def at(w0: int, h0: int, focal=focal, w_orig=w_orig, h_orig=h_orig) -> tuple[float, float, float, float]:
            return focal * w0 / w_orig, focal * h0 / h_orig, 0.5 * w0, 0.5 * h0

        px = load_pixels(f, at, where=f"{img_dir.name}/{f.name}", width=width, mask=masks[i] if masks else None)
        if pixels and px.size != pixels[0].size:
            raise DataError(f"inconsistent image sizes: {f.name} is {px.size[0]}x{px.size[1]} but {files[0].name} is "
                            f"{pixels[0].size[0]}x{pixels[0].size[1]}")
        pixels.append(px)
    names = [f.stem for f in files]
    meta: dict = {
        "source": str(folder),
        "format": "llff",
        "images_dir": str(img_dir),
        "original_size": [int(hwf[0, 1]), int(hwf[0, 0])],
        "bounds": {n: [float(b[0]), float(b[1])] for n, b in zip(names, bounds)},
        "near_far": [float(bounds[:, 0].min()), float(bounds[:, 1].max())],
        "notes": [f"LLFF images from {img_dir.name}/, poses and near/far bounds from {POSES_BOUNDS}"],
    }
    if masks:
        meta["masks"] = masks_meta(masks)
    if width is not None:
        meta["width"] = width
    return Views(
        images=torch.from_numpy(stack_images([p.image for p in pixels])),
        c2w=torch.from_numpy(llff_to_opengl_c2w(poses)).float(),
        intrinsics=torch.tensor([p.intrinsics for p in pixels], dtype=torch.float32),
        names=names,
        meta=meta,
    )


def _read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> (poses [N, 3, 4] LLFF camera-to-world, bounds [N, 2] near/far, hwf [N, 3] at the original size)."""
    try:
        arr = np.load(path)
    except (OSError, ValueError) as e:
        raise DataError(f"{path}: cannot be read: {e}") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or len(arr) == 0:
        raise DataError(f"{path}: expected an N x 17 array (3x5 pose and near, far per image), got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise DataError(f"{path}: contains NaN or infinity")
    mats = arr[:, :15].reshape(-1, 3, 5)
    poses, hwf, bounds = mats[:, :, :4], mats[:, :, 4], arr[:, 15:17]
    rot = poses[:, :, :3]
    err = np.abs(rot.transpose(0, 2, 1) @ rot - np.eye(3)).max(axis=(1, 2))
    bad = np.nonzero((err > 1e-3) | (np.linalg.det(rot) < 0))[0]
    if len(bad):
        raise DataError(f"{path}: row {bad[0]} is not a rotation (axes not orthonormal, or a reflection)")
    bad = np.nonzero((hwf <= 0).any(axis=1))[0]
    if len(bad):
        raise DataError(f"{path}: row {bad[0]} has a non-positive H, W or focal: {hwf[bad[0]].tolist()}")
    bad = np.nonzero((bounds[:, 0] <= 0) | (bounds[:, 1] <= bounds[:, 0]))[0]
    if len(bad):
        raise DataError(f"{path}: row {bad[0]} has bounds near {bounds[bad[0], 0]:.4g}, far {bounds[bad[0], 1]:.4g}; "
                        "expected 0 < near < far")
    return poses, bounds, hwf


def choose_image_dir(folder: Path, width: int | None) -> tuple[Path, list[Path]]:
    """The image folder to load at ``width``: the smallest at least that wide, else the largest.

    Candidates are ``images/`` and ``images_*/`` (``images_4``, ``images_1008x756``, ...) holding
    images; each is as wide as its first image.
    """
    cands = []
    for d in sorted(p for p in folder.iterdir() if p.is_dir() and re.fullmatch(r"images(_\w+)?", p.name)):
        files = list_image_files(d)
        if files:
            cands.append((_image_width(files[0]), d, files))
    if not cands:
        raise DataError(f"{folder}: {POSES_BOUNDS} but no images/ or images_N/ folder with images")
    wide_enough = [c for c in cands if width is not None and c[0] >= width]
    _, d, files = min(wide_enough, key=lambda c: c[0]) if wide_enough else max(cands, key=lambda c: c[0])
    return d, files


def _image_width(path: Path) -> int:
    return int(read_raw(path).shape[1])
