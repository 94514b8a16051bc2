"""One view's pixels as every loader prepares them, in one order: read, mask composited as alpha,
lens distortion undone (both at the file's native size, which masks and calibration belong to),
then downscaled. Loaders own the poses; this module owns what happens to the pixels."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from agent.camera import distortion_coeffs

from agent.data.images import read_image, read_mask, resize_depth, resize_image, target_size
from agent.data.lens import Lens, Undistortion, undistortion
from agent.data.masks import apply_mask
from agent.data.views import DataError, Views

__all__ = ["Pixels", "load_pixels", "prepare_depth", "lens_meta", "undistort_views"]

Intrinsics = tuple[float, float, float, float]  # fx, fy, cx, cy


@dataclass
class Pixels:
    image: np.ndarray  # [h, w, 3|4] float32 at the target size
    intrinsics: Intrinsics  # of the (pinhole) image at the target size
    native_size: tuple[int, int]  # (W, H) of the file
    scale: tuple[float, float]  # (sx, sy): target size / native size
    undistortion: Undistortion | None  # what was done to the lens, at the native size

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[0])


def load_pixels(
    path: Path,
    intrinsics: Intrinsics | Callable[[int, int], Intrinsics],
    *,
    where: str,
    width: int | None = None,
    mask: Path | None = None,
    lens: Lens | None = None,
) -> Pixels:
    """The image at ``path`` ready for :class:`Views`: masked, undistorted (when ``lens``), downscaled to ``width``.

    intrinsics: of the file at its native size, or a function of that size ``(W, H)`` giving them.
    """
    if not path.is_file():
        raise DataError(f"{where}: image not found: {path}")
    img = read_image(path)
    h0, w0 = img.shape[:2]
    if mask is not None:
        img = apply_mask(img, read_mask(mask), f"{where} ({mask.name})")
    k = intrinsics(w0, h0) if callable(intrinsics) else intrinsics
    und = None
    if lens is not None:
        und = undistortion(tuple(float(x) for x in k), w0, h0, lens)  # type: ignore[arg-type]
        img, k = und.image(img), und.intrinsics
    new_w, new_h = target_size(w0, h0, width, where)
    sx, sy = new_w / w0, new_h / h0
    img = resize_image(img, new_w, new_h)
    return Pixels(img, (k[0] * sx, k[1] * sy, k[2] * sx, k[3] * sy), (w0, h0), (sx, sy), und)


def prepare_depth(depth: np.ndarray, pixels: Pixels, sparse: bool, where: str) -> np.ndarray:
    """A depth map [H0, W0] of the native image -> [h, w] of the prepared one (undistorted, resized)."""
    if depth.shape != pixels.native_size[::-1]:
        w, h = pixels.native_size
        if pixels.undistortion is not None:
            raise DataError(f"{where}: depth is {depth.shape[1]}x{depth.shape[0]}, its image {w}x{h}; "
                            "undistorting needs them at one size")
        return resize_depth(depth, *pixels.size, sparse=sparse)
    if pixels.undistortion is not None:
        depth = pixels.undistortion.depth(depth, sparse=sparse)
    return resize_depth(depth, *pixels.size, sparse=sparse)


def lens_meta(done: list[Undistortion], ignored: list[str]) -> tuple[dict | None, list[str]]:
    """(``meta['lens']``, notes) of a load that undid the lenses ``done`` and ignored ``ignored``.

    ``None`` when the cameras are pinholes. One note per distinct camera, which says what was done.
    """
    if not done and not ignored:
        return None, []
    cams = {(u.lens, u.size, u.source_intrinsics): u for u in done}
    notes = [f"lens distortion undone: {u.describe()}" for u in list(cams.values())[:4]]
    if len(cams) > 4:
        notes.append(f"... and {len(cams) - 4} more cameras undistorted the same way")
    models = sorted({u.lens.name for u in done} | set(ignored))
    meta = {
        "models": models,
        "undistorted": bool(done),
        "done": "undistorted at load (OpenCV), pinhole intrinsics replaced" if done else "ignored (undistort=False)",
    }
    return meta, notes


def undistort_views(views: Views) -> Views:
    """Views still as a lens recorded them (``meta["distortion"]``, e.g. the procedural lens) ->
    pinhole views, undone as a loader undoes a dataset's lens (the same :func:`undistortion`)."""
    coeffs = distortion_coeffs(views.meta.get("distortion"))
    if coeffs is None:
        return views
    lens = Lens("radtan", coeffs, "OpenCV (recorded)")
    done, images, depths, intr = [], [], [], []
    for i in range(len(views)):
        und = undistortion(tuple(float(x) for x in views.intrinsics[i]), views.width, views.height, lens)
        done.append(und)
        images.append(und.image(views.images[i].numpy()))
        intr.append(und.intrinsics)
        if views.depth is not None:
            depths.append(und.depth(views.depth[i].numpy(), sparse=bool(views.meta.get("depth_sparse"))))
    meta = {k: v for k, v in views.meta.items() if k != "distortion"}
    meta["lens"], notes = lens_meta(done, [])
    meta["notes"] = list(meta.get("notes", [])) + notes
    return Views(torch.from_numpy(np.stack(images)), views.c2w, torch.tensor(intr, dtype=torch.float32),
                 list(views.names), torch.from_numpy(np.stack(depths)) if depths else None, meta)
