"""Image and depth files of the datasets: reading, downscaling, naming.

Images are float32 [H, W, 3|4] straight colour in [0, 1], RGB(A) order; depth maps are z-depth
[H, W], 0 = unknown (:mod:`agent.data.views`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from agent.data.views import DataError, Views

__all__ = [
    "IMAGE_EXTENSIONS",
    "read_image",
    "read_raw",
    "imread",
    "read_mask",
    "target_size",
    "resize_image",
    "resize_depth",
    "resize_views",
    "list_image_files",
    "unique_names",
    "stack_images",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".tif", ".tiff", ".bmp", ".webp")


def read_image(path: str | Path) -> np.ndarray:
    """Any 8/16-bit or float grey/RGB/RGBA file -> float32 [H, W, 3|4] straight colour in [0, 1], RGB(A) order."""
    img = _read_unit(path)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    elif img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    else:
        raise DataError(f"{path}: {img.shape[2]} channels, expected 1, 3 or 4")
    return np.ascontiguousarray(img)


def read_mask(path: str | Path) -> np.ndarray:
    """A mask file (grey 0-255 or 0-65535, soft edges kept) -> float32 [H, W] in [0, 1], 1 = object.

    Colour masks count by their grey level; an alpha channel of the mask file is not used.
    """
    m = _read_unit(path)
    if m.ndim == 3:
        m = m[:, :, 0] if m.shape[2] == 1 else cv2.cvtColor(np.ascontiguousarray(m[:, :, :3]), cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(m, dtype=np.float32)


def imread(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray | None:
    """``cv2.imread``, without OpenCV's own log line on a file it cannot decode: the caller
    reports that in one line of its own (the CLI's ``error: ...``)."""
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        return cv2.imread(str(path), flags)
    finally:
        log.setLogLevel(level)


def read_raw(path: str | Path) -> np.ndarray:
    """A file's pixels as cv2 decodes them (BGR(A) order, its own dtype); DataError if it is no image."""
    img = imread(path)
    if img is None:
        raise DataError(f"{path}: cannot be read as an image")
    return img


def _read_unit(path: str | Path) -> np.ndarray:
    """A file's pixels as cv2 decodes them (BGR(A) order), float32 in [0, 1]."""
    img = read_raw(path)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype)
    if scale is None and not np.issubdtype(img.dtype, np.floating):
        raise DataError(f"{path}: unsupported pixel type {img.dtype}")
    return np.clip(img.astype(np.float32) / (scale or 1.0), 0.0, 1.0)


def target_size(width: int, height: int, target_width: int | None, where: str) -> tuple[int, int]:
    """(width, height) of an image downscaled to ``target_width`` (None: as it is), aspect kept."""
    if target_width is None or target_width == width:
        return width, height
    if target_width > width:
        raise DataError(f"{where}: width {target_width} is larger than the images' {width}; only downscaling is supported")
    return target_width, max(1, round(height * target_width / width))


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-downscale an image [H, W, C] float32 to [height, width, C].

    RGBA is resized premultiplied and divided back, so that the (meaningless) colour of fully
    transparent pixels cannot bleed into the object's edge as a dark or white fringe.
    """
    if img.shape[1] == width and img.shape[0] == height:
        return img
    if img.shape[2] == 4:
        alpha = img[:, :, 3:4]
        premul = np.concatenate([img[:, :, :3] * alpha, alpha], axis=2)
        out = cv2.resize(premul, (width, height), interpolation=cv2.INTER_AREA)
        a = out[:, :, 3:4]
        rgb = np.where(a > 1e-6, out[:, :, :3] / np.maximum(a, 1e-6), 0.0)
        return np.clip(np.concatenate([rgb, a], axis=2), 0.0, 1.0).astype(np.float32)
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32)


def resize_depth(depth: np.ndarray, width: int, height: int, sparse: bool = False) -> np.ndarray:
    """Resize a z-depth map [H, W] without ever blending depths across edges.

    Dense maps: nearest neighbour taken at the *centre* of each target pixel
    (source index ``floor((u + 0.5) * W / width)``), consistent with the intrinsics scaling.
    Sparse maps (mostly 0 = unknown): every known sample is moved to the target pixel that
    contains it, the nearest surface winning, so that downscaling never drops SfM points.
    """
    h, w = depth.shape
    if (w, h) == (width, height):
        return depth
    if sparse:
        rows, cols = np.nonzero(depth > 0)
        vals = depth[rows, cols]
        out = np.full((height, width), np.inf, dtype=np.float64)
        r = np.minimum(((rows + 0.5) * height / h).astype(np.int64), height - 1)
        c = np.minimum(((cols + 0.5) * width / w).astype(np.int64), width - 1)
        np.minimum.at(out, (r, c), vals)
        out[np.isinf(out)] = 0.0
        return out.astype(np.float32)
    src_r = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    src_c = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return np.ascontiguousarray(depth[src_r[:, None], src_c[None, :]]).astype(np.float32)


def resize_views(views: Views, width: int) -> Views:
    """Downscale every image (area), depth map (nearest / sparse-preserving) and intrinsics."""
    new_w, new_h = target_size(views.width, views.height, width, "resize")
    if (new_w, new_h) == (views.width, views.height):
        return views
    sx, sy = new_w / views.width, new_h / views.height
    images = np.stack([resize_image(im, new_w, new_h) for im in views.images.numpy()])
    depth = None
    if views.depth is not None:
        sparse = bool(views.meta.get("depth_sparse", False))
        depth = torch.from_numpy(np.stack([resize_depth(d, new_w, new_h, sparse) for d in views.depth.numpy()]))
    intr = views.intrinsics * torch.tensor([sx, sy, sx, sy], dtype=views.intrinsics.dtype)
    meta = dict(views.meta, resized_from=[views.width, views.height])
    return Views(torch.from_numpy(images), views.c2w.clone(), intr, list(views.names), depth, meta)


def list_image_files(folder: Path) -> list[Path]:
    """The image files directly in ``folder`` (none if it is not a folder), sorted by name."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_EXTENSIONS)


def unique_names(paths: list[str]) -> list[str]:
    """File stems when they are unique, else the relative paths with '/' turned into '_'."""
    stems = [Path(p).stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    flat = [str(Path(p).with_suffix("")).lstrip("./").replace("/", "_").replace("\\", "_") for p in paths]
    if len(set(flat)) != len(flat):
        raise DataError(f"duplicate image names: {sorted({n for n in flat if flat.count(n) > 1})[:5]}")
    return flat


def stack_images(images: list[np.ndarray]) -> np.ndarray:
    """[H, W, 3|4] images -> [M, H, W, C]; when some have alpha, the others get alpha 1."""
    channels = max(im.shape[2] for im in images)
    if channels == 4:
        images = [im if im.shape[2] == 4 else np.concatenate([im, np.ones_like(im[:, :, :1])], 2) for im in images]
    return np.stack(images)
