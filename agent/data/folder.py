"""The on-disk form of a set of views (a robot folder) and the split's side files.

A robot folder is a nerfstudio-style dataset, so it loads back with
:func:`agent.data.loaders.load_views` and opens in other tools::

    transforms.json     camera_model PINHOLE, w, h, fl_x, fl_y, cx, cy (top level when all views
                        share them, else per frame), frames [{file_path, transform_matrix
                        (OpenGL camera-to-world), depth_file_path?}], depth_unit_scale_factor 1.0;
                        camera_model OPENCV and k1, k2, p1, p2 when the views carry a lens
                        distortion (``meta["distortion"]``): the images stay as the lens saw them
    images/<name>.png   8-bit RGBA (RGB when the source has no alpha)
    depth/<name>.npy    float32 z-depth in the folder's units, 0 = unknown (only with a depth prior)

A split directory adds ``scene.json`` (what every agent may read: the shared field box) and
``truth.json`` (evaluation only: the true relative poses and depth-prior scale/shift; the agent
never reads it). :func:`read_scene` and :func:`read_truth` read them back.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from agent.camera import DISTORTION_KEYS, distortion_coeffs
from agent.data.views import DataError, Views
from agent.files import read_json

__all__ = ["write_views_folder", "write_json", "write_png", "matrix_to_list", "read_scene", "read_truth", "SceneInfo"]


def matrix_to_list(t: Tensor | np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(t, dtype=np.float64)]


def write_json(path: Path, data: Any) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n")


def write_png(path: Path, img: np.ndarray) -> None:
    """img: [H, W, 3|4] float in [0, 1] -> 8-bit PNG (OpenCV wants BGR(A))."""
    q = np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    q = q[:, :, [2, 1, 0, 3]] if q.shape[2] == 4 else q[:, :, ::-1]
    if not cv2.imwrite(str(path), np.ascontiguousarray(q)):
        raise DataError(f"cannot write {path}")


def write_views_folder(
    views: Views,
    folder: str | Path,
    *,
    write_poses: bool = True,
    frame_extra: list[dict] | None = None,
    top_extra: dict | None = None,
) -> dict | None:
    """Write ``views`` as a nerfstudio-style folder; returns the transforms.json content.

    write_poses=False writes the images only (an "images-only" robot that must run its own SfM).
    frame_extra: one dict per view merged into its frame entry (e.g. ``seen_by``);
    top_extra: merged into the top level. Depth is written when ``views.depth`` is set.
    """
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    images = views.images.numpy()
    for name, img in zip(views.names, images):
        write_png(folder / "images" / f"{name}.png", img)
    if not write_poses:
        return None
    if views.depth is not None:
        (folder / "depth").mkdir(exist_ok=True)
        for name, d in zip(views.names, views.depth.numpy()):
            np.save(folder / "depth" / f"{name}.npy", d.astype(np.float32))

    intr = views.intrinsics.to(torch.float64)
    shared = bool((intr == intr[0]).all())
    lens = distortion_coeffs(views.meta.get("distortion"))
    top: dict[str, Any] = {"camera_model": "OPENCV" if lens else "PINHOLE", "w": views.width, "h": views.height}
    if shared:
        top.update(zip(("fl_x", "fl_y", "cx", "cy"), (float(x) for x in intr[0])))
    if lens:  # one lens for all views, in nerfstudio's names
        top.update(zip(DISTORTION_KEYS, lens))
    if views.depth is not None:
        top["depth_unit_scale_factor"] = 1.0
    if top_extra:
        top.update(top_extra)
    frames = []
    for i, name in enumerate(views.names):
        fr: dict[str, Any] = {"file_path": f"images/{name}.png", "transform_matrix": matrix_to_list(views.c2w[i])}
        if not shared:
            fr.update(zip(("fl_x", "fl_y", "cx", "cy"), (float(x) for x in intr[i])))
        if views.depth is not None:
            fr["depth_file_path"] = f"depth/{name}.npy"
        if frame_extra:
            fr.update(frame_extra[i])
        frames.append(fr)
    top["frames"] = frames
    write_json(folder / "transforms.json", top)
    return top


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise DataError(f"{path}: not found; expected the {what} written by `dinerf-agent split`")
    data = read_json(path, DataError)
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object")
    return data


@dataclass
class SceneInfo:
    """What every robot of a split may know: the field box in the shared frame and who defines it."""

    # [4, 4] float64 similarity: shared frame g -> box coordinates [-1, 1]^3. None when the split
    # cannot know it: robots with images only, whose shared frame is the reference's own SfM frame
    # (the reference derives the box from its SfM at start and shares it with the keyframes).
    box_from_shared: Tensor | None
    reference_id: int
    # what the robots' images are, for the settings they call for (agent.defaults.Capture): None
    # in a scene.json from before it was written
    capture: dict | None = None


def read_scene(path: str | Path) -> SceneInfo:
    """Read ``scene.json`` from a split directory, a robot folder inside it, or the file itself."""
    path = Path(path)
    if path.is_dir():
        path = path / "scene.json" if (path / "scene.json").is_file() else path.parent / "scene.json"
    data = _read_json(path, "scene.json")
    try:
        raw = data["box_from_shared"]
        box = None if raw is None else torch.tensor(raw, dtype=torch.float64)
        ref = int(data["reference_id"])
        capture = data.get("capture")
        if capture is not None:
            capture = {"unbounded": bool(capture["unbounded"]), "width": int(capture["width"])}
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(f"{path}: expected 'box_from_shared' (4x4, or null), 'reference_id' and optionally "
                        f"'capture' (unbounded, width): {e}") from None
    if box is not None and (box.shape != (4, 4) or not torch.isfinite(box).all()):
        raise DataError(f"{path}: box_from_shared must be a finite 4x4 matrix (or null)")
    return SceneInfo(box, ref, capture)


def read_truth(path: str | Path) -> dict:
    """Read ``truth.json`` (evaluation only). Matrices come back as float64 tensors [4, 4]."""
    path = Path(path)
    if path.is_dir():
        path = path / "truth.json"
    data = _read_json(path, "truth.json")
    for rob in data.get("robots", {}).values():
        for key in ("T_world_from_local", "T_shared_from_local"):
            if key in rob:
                rob[key] = torch.tensor(rob[key], dtype=torch.float64)
    return data
