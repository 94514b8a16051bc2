"""Object masks of a dataset, composited as alpha (the straight RGBA of :class:`~agent.data.views.Views`).

Where the masks are, for any format:

- nerfstudio's per-frame ``mask_path`` in transforms.json (relative to the json);
- else a ``masks*`` folder beside the images' folder: ``masks/`` for ``images/``, ``masks_4/`` for
  ``images_4/`` (another ``masks``/``masks_N`` when the matching one is absent, then resized to
  the images), or ``masks/`` among images that are not in an ``images*`` folder. A mask is named
  like its image's stem, with or without ``_mask``, any image extension, or as COLMAP names them
  (``<image name>.png``).

A mask (grey, soft edges kept) becomes the alpha of its image, or multiplies the alpha it has. It
is applied at the native size, so that it is undistorted and downscaled with its image. Masks for
only some images are an error: a capture half composited would describe two different scenes.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from agent.data.images import IMAGE_EXTENSIONS
from agent.data.views import DataError

__all__ = ["mask_folder_for", "find_masks", "check_mask_paths", "apply_mask", "masks_meta"]


def mask_folder_for(image_dir: Path) -> Path | None:
    """The folder holding the masks of the images in ``image_dir``; None when there is none."""
    if not image_dir.name.startswith("images"):
        return image_dir / "masks" if _has_images(image_dir / "masks") else None
    exact = image_dir.parent / image_dir.name.replace("images", "masks", 1)
    if _has_images(exact):
        return exact
    others = [p for p in image_dir.parent.glob("masks*") if re.fullmatch(r"masks(_\d+)?", p.name) and _has_images(p)]
    return min(others, key=lambda p: int(p.name[6:] or 1)) if others else None  # the finest


def find_masks(images: list[Path], root: Path | None = None, where: str = "") -> list[Path] | None:
    """The mask file of every image, from the masks folder beside its folder; None when no image has one.

    images: the image files; root: the folder their names are relative to (COLMAP's image names
    may hold sub-folders), else each image's own folder. A missing mask among found ones is an
    error naming the first image without one.
    """
    found: list[Path | None] = []
    looked: list[str] = []
    indexes: dict[Path, dict[str, Path]] = {}
    for img in images:
        base = root if root is not None else img.parent
        folder = mask_folder_for(base)
        rel = img.relative_to(base) if root is not None else Path(img.name)
        if folder is None:
            found.append(None)
            looked.append(f"no masks folder beside {base}")
            continue
        sub = folder / rel.parent
        index = indexes.setdefault(sub, _index(sub))
        stem = rel.stem
        found.append(next((index[k] for k in (stem, stem + "_mask", rel.name) if k in index), None))
        looked.append(f"looked in {sub} for {stem}, {stem}_mask or {rel.name} with an image extension")
    if all(m is None for m in found):
        return None
    missing = found.index(None) if None in found else -1
    if missing >= 0:
        have = sum(m is not None for m in found)
        raise DataError(f"{where}no mask for {images[missing].name} ({looked[missing]}); {have} of {len(images)} "
                        "images have one, and masks must cover every image or none")
    return found  # type: ignore[return-value]


def check_mask_paths(paths: list[Path | None], labels: list[str], where: str = "") -> list[Path] | None:
    """Masks named per image (nerfstudio's ``mask_path``): all or none, and every file present."""
    if all(p is None for p in paths):
        return None
    for p, label in zip(paths, labels):
        if p is None:
            raise DataError(f"{where}{label} has no mask_path while others have one; masks must cover every image or none")
        if not p.is_file():
            raise DataError(f"{where}{label}: mask not found: {p}")
    return paths  # type: ignore[return-value]


def apply_mask(img: np.ndarray, mask: np.ndarray, where: str) -> np.ndarray:
    """img [H, W, 3|4], mask [h, w] in [0, 1] -> RGBA [H, W, 4] with alpha = alpha * mask.

    A mask of another size with the image's aspect ratio (a mask folder of another
    downscale) is resized to the image first.
    """
    h, w = img.shape[:2]
    if mask.shape != (h, w):
        mh, mw = mask.shape
        if abs(mw / mh - w / h) > 0.01 * w / h:
            raise DataError(f"{where}: mask is {mw}x{mh}, its image {w}x{h}: not the same aspect ratio")
        mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA if mw > w else cv2.INTER_LINEAR)
    mask = np.clip(mask, 0.0, 1.0)[:, :, None]
    if img.shape[2] == 4:
        return np.concatenate([img[:, :, :3], img[:, :, 3:4] * mask], axis=2)
    return np.concatenate([img, mask], axis=2).astype(np.float32)


def masks_meta(masks: list[Path], source: str = "folder") -> dict:
    """``meta['masks']`` of a load that composited ``masks``; source: ``folder`` or ``mask_path``."""
    return {"count": len(masks), "from": source, "folders": sorted({str(m.parent) for m in masks})}


def _index(folder: Path) -> dict[str, Path]:
    """{stem: file} of the image files in ``folder`` (the first by name when two share a stem)."""
    if not folder.is_dir():
        return {}
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in {e.lower() for e in IMAGE_EXTENSIONS}:
            out.setdefault(p.stem, p)
    return out


def _has_images(folder: Path) -> bool:
    return folder.is_dir() and any(p.suffix.lower() in {e.lower() for e in IMAGE_EXTENSIONS} for p in folder.iterdir())
