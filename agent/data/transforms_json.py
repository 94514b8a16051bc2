"""``transforms.json`` datasets: the Blender, nerfstudio and instant-ngp conventions.

All three store OpenGL camera-to-world poses, so only the intrinsics differ: ``fl_x``/``fl_y``
(nerfstudio, instant-ngp) or ``camera_angle_x``/``camera_angle_y`` (Blender).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch

from agent.camera import focal_from_fov
from agent.data.frames import Pixels, lens_meta, load_pixels, prepare_depth
from agent.data.images import IMAGE_EXTENSIONS, imread, stack_images, unique_names
from agent.data.lens import Lens, transforms_lens
from agent.data.masks import check_mask_paths, find_masks, masks_meta
from agent.data.views import EXPECTED_LAYOUTS, DataError, Views
from agent.files import read_json
from agent.progress import track

__all__ = ["load_transforms"]

_UNSUPPORTED_NS_MODELS = {"FISHEYE", "EQUIRECTANGULAR", "FOV", "THIN_PRISM_FISHEYE", "FISHEYE624"}
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def load_transforms(json_path: str | Path, *, width: int | None = None, load_depth: bool = True,
                    undistort: bool = True) -> Views:
    """Read a Blender / nerfstudio / instant-ngp ``transforms*.json``.

    Poses are OpenGL camera-to-world in all three formats and are kept in the file's units
    (instant-ngp's ``scale``/``offset``/``aabb_scale`` are rendering hints of that program and
    are only copied into ``meta``). ``file_path`` is relative to the json, with or without its
    extension. Images keep their alpha; frames without alpha get alpha 1 when others have it.
    Masks (``mask_path``, or a ``masks/`` folder beside ``images/``) become alpha
    (:mod:`agent.data.masks`); OPENCV and OPENCV_FISHEYE distortion is undone unless
    ``undistort`` is False, when radial-tangential distortion is ignored with a note.
    """
    json_path = Path(json_path)
    top, frames = _read_json(json_path)
    model = str(top.get("camera_model", "")).upper()
    if not undistort and (model == "OPENCV_FISHEYE" or top.get("is_fisheye")):
        raise DataError(f"{json_path}: camera_model {model or 'is_fisheye'} is not supported without undistortion; "
                        "a fisheye cannot pass for a pinhole: load with undistort=True (the default)")
    paths = [_frame_image(frame, i, json_path) for i, frame in enumerate(frames)]
    masks, masks_from = _frame_masks(frames, paths, json_path)
    base = json_path.parent
    notes: set[str] = set()
    dinerf = top["dinerf"] if isinstance(top.get("dinerf"), dict) else {}  # written by `dinerf-agent split`
    # sparse depth (SfM points) must be resized point by point, not by nearest neighbour
    sparse_depth = bool(dinerf.get("depth_sparse", False))
    factor = _num(top, "depth_unit_scale_factor", str(json_path))
    loaded: list[_Frame] = []
    depths: list[np.ndarray | None] = []
    for i, frame in enumerate(track(frames, f"loading {json_path.parent.name or json_path.name}")):
        f = _read_frame(top, frame, i, json_path, paths[i], masks[i] if masks else None, width, undistort, notes)
        if loaded and loaded[0].size != f.size:
            raise DataError(
                f"inconsistent image sizes: {f.file_path} is {f.size[0]}x{f.size[1]} but {loaded[0].file_path} is "
                f"{loaded[0].size[0]}x{loaded[0].size[1]}" + ("" if width is None else f" (after resizing to width {width})")
            )
        depth = None
        dfp = frame.get("depth_file_path")
        if load_depth and dfp:
            dpath = base / str(dfp)
            if not dpath.is_file():
                raise DataError(f"{f.where}: depth file not found: {dpath}")
            depth = prepare_depth(_read_depth_file(dpath, factor, f.where), f.pixels, sparse_depth, f.where)
        loaded.append(f)
        depths.append(depth)

    depth_t = None
    if any(d is not None for d in depths):
        w, h = loaded[0].size
        depth_t = torch.from_numpy(np.stack([d if d is not None else np.zeros((h, w), np.float32) for d in depths]))
    meta = _meta(json_path, top, frames, notes, sparse_depth, width)
    _describe_pixels(meta, loaded, masks, masks_from)
    return Views(
        images=torch.from_numpy(stack_images([f.pixels.image for f in loaded])),
        c2w=torch.from_numpy(np.stack([f.pose for f in loaded])).float(),
        intrinsics=torch.tensor([f.pixels.intrinsics for f in loaded], dtype=torch.float32),
        names=unique_names([f.file_path for f in loaded]),
        depth=depth_t,
        meta=meta,
    )


def _describe_pixels(meta: dict, loaded: list["_Frame"], masks: list[Path] | None, masks_from: str) -> None:
    """``meta['masks']``, ``meta['distortion']`` and their notes: what was done to the pixels."""
    if masks:
        meta["masks"] = masks_meta(masks, masks_from)
    done = [f.pixels.undistortion for f in loaded if f.pixels.undistortion is not None]
    ignored = sorted({f.ignored for f in loaded if f.ignored})
    lens, notes = lens_meta(done, ignored)
    if lens is not None:
        meta["lens"] = lens
        meta["notes"] = sorted(set(meta["notes"]) | set(notes))


def _read_json(json_path: Path) -> tuple[dict, list]:
    """The top-level object and its non-empty ``frames`` of a transforms file, checked."""
    if not json_path.is_file():
        raise DataError(f"{json_path}: no such file; {EXPECTED_LAYOUTS}")
    top = read_json(json_path, DataError)
    if not isinstance(top, dict):
        raise DataError(f"{json_path}: expected a JSON object with a 'frames' list")
    frames = top.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{json_path}: no frames; expected a non-empty 'frames' list of {{file_path, transform_matrix}}")
    model = str(top.get("camera_model", "")).upper()
    if model in _UNSUPPORTED_NS_MODELS:
        raise DataError(f"{json_path}: camera_model {model} is not supported; expected PINHOLE, OPENCV or OPENCV_FISHEYE")
    return top, frames


@dataclass
class _Frame:
    file_path: str  # as written in the json
    where: str  # for error messages
    pixels: Pixels  # the image at the target size, its intrinsics, what was done to it
    pose: np.ndarray  # [4, 4] OpenGL c2w
    ignored: str = ""  # the name of a lens distortion left in the image (undistort=False)

    @property
    def size(self) -> tuple[int, int]:  # (W, H) at the target size
        return self.pixels.size


def _frame_image(frame: Any, i: int, json_path: Path) -> Path:
    """The image file of frame ``i``, checked to exist; the frame is checked to be one."""
    where = f"{json_path.name}: frame {i}"
    if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
        raise DataError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
    fp = str(frame["file_path"])
    img_path = _resolve_image(json_path.parent, fp)
    if img_path is None:
        raise DataError(f"{where} ({fp}): image not found: {json_path.parent / fp} (also tried .png/.jpg/.jpeg)")
    return img_path


def _frame_masks(frames: list, paths: list[Path], json_path: Path) -> tuple[list[Path] | None, str]:
    """The frames' masks: nerfstudio's ``mask_path`` (all frames or none), else a masks folder beside the images."""
    named = [json_path.parent / str(f["mask_path"]) if f.get("mask_path") else None for f in frames]
    labels = [f"frame {i} ({f['file_path']})" for i, f in enumerate(frames)]
    masks = check_mask_paths(named, labels, f"{json_path.name}: ")
    if masks is not None:
        return masks, "mask_path"
    return find_masks(paths, where=f"{json_path.name}: "), "folder"


def _read_frame(top: dict, frame: dict, i: int, json_path: Path, img_path: Path, mask: Path | None,
                width: int | None, undistort: bool, notes: set[str]) -> _Frame:
    """One frame's pixels (masked, undistorted, downscaled to ``width``) and pose; depth is read by the caller."""
    fp = str(frame["file_path"])
    where = f"{json_path.name}: frame {i} ({fp})"
    pose = _check_pose(frame["transform_matrix"], where)
    get = _getter(top, frame, where)
    lens = _frame_lens(top, get, where)
    ignored = ""
    if lens is not None and not undistort:
        notes.add("lens distortion ignored (" + ", ".join(k for k in _DISTORTION_KEYS if get(k)) + ")")
        lens, ignored = None, lens.name
    pixels = load_pixels(img_path, lambda w0, h0: _frame_intrinsics(get, w0, h0, where, notes), where=where,
                         width=width, mask=mask, lens=lens)
    return _Frame(fp, where, pixels, pose, ignored)


def _frame_lens(top: dict, get: Callable[[str], float | None], where: str) -> Lens | None:
    """The frame's lens distortion (None: a pinhole)."""
    model = str(top.get("camera_model", "")).upper()
    fisheye = bool(top.get("is_fisheye"))
    if model != "OPENCV_FISHEYE" and not fisheye and not any(get(k) for k in _DISTORTION_KEYS):
        return None
    return transforms_lens(model, get, fisheye, where)


def _meta(json_path: Path, top: dict, frames: list, notes: set[str], sparse_depth: bool, width: int | None) -> dict:
    meta: dict[str, Any] = {
        "source": str(json_path),
        "format": _transforms_flavour(top, frames),
        "notes": sorted(notes),
        "depth_sparse": sparse_depth,
    }
    for key in ("aabb_scale", "scale", "offset", "applied_transform", "camera_model"):
        if key in top:
            meta[key] = top[key]
    if isinstance(top.get("scene_box_world"), dict):
        meta["scene_box_world"] = top["scene_box_world"]
    if width is not None:
        meta["width"] = width
    return meta


def _transforms_flavour(top: dict, frames: list) -> str:
    if "fl_x" in top or any(isinstance(f, dict) and "fl_x" in f for f in frames):
        return "nerfstudio" if "camera_model" in top else "instant-ngp"
    return "blender"


def _check_pose(mat: Any, where: str) -> np.ndarray:
    """A camera-to-world matrix from JSON: 3x4 or 4x4, finite, invertible. -> [4, 4] float64.

    A rotation block with a little scale or shear (some exporters) is re-orthonormalised by SVD;
    one that is singular is an error rather than a silently broken camera.
    """
    try:
        m = np.asarray(mat, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{where}: transform_matrix is not a numeric matrix") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise DataError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {m.shape}")
    if not np.isfinite(m).all():
        raise DataError(f"{where}: transform_matrix contains NaN or infinity")
    rot = m[:3, :3]
    det = np.linalg.det(rot)
    if abs(det) < 1e-6 or not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
        raise DataError(f"{where}: transform_matrix is not invertible (det of rotation {det:.3g}, last row {m[3].tolist()})")
    u, _, vt = np.linalg.svd(rot)
    ortho = u @ vt
    if np.linalg.det(ortho) < 0:
        raise DataError(f"{where}: transform_matrix is a reflection (det < 0), not a camera pose")
    m = m.copy()
    m[:3, :3] = ortho
    return m


def _resolve_image(base: Path, file_path: str) -> Path | None:
    p = base / file_path
    if p.is_file():
        return p
    if p.suffix.lower() not in IMAGE_EXTENSIONS:  # Blender writes "./train/r_0" without extension
        for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".exr"):
            q = p.with_name(p.name + ext)
            if q.is_file():
                return q
    return None


def _num(d: dict, key: str, where: str) -> float | None:
    if key not in d or d[key] is None:
        return None
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise DataError(f"{where}: '{key}' must be a finite number, got {v!r}")
    return float(v)


def _getter(top: dict, frame: dict, where: str) -> Callable[[str], float | None]:
    """``get(key)``: a number of the frame, else of the file (per-frame keys override top-level ones)."""

    def get(key: str) -> float | None:
        v = _num(frame, key, where)
        return v if v is not None else _num(top, key, where)

    return get


def _frame_intrinsics(get: Callable[[str], float | None], img_w: int, img_h: int, where: str,
                      notes: set[str]) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) at the image's native size.

    Precedence follows the formats: ``fl_x``/``fl_y`` (nerfstudio, instant-ngp) over
    ``camera_angle_x``/``camera_angle_y`` (Blender); a missing ``fl_y`` means square pixels; a
    missing ``cx``/``cy`` means the image centre. When the declared ``w``/``h`` differ from the
    image on disk (a downscaled copy of the images), the intrinsics are scaled to the image.
    """
    decl_w, decl_h = get("w"), get("h")
    w = decl_w if decl_w else float(img_w)
    h = decl_h if decl_h else float(img_h)
    fx, fy = get("fl_x"), get("fl_y")
    ang_x, ang_y = get("camera_angle_x"), get("camera_angle_y")
    if fx is None and ang_x is not None:
        fx = focal_from_fov(w, ang_x)
    if fy is None and ang_y is not None:
        fy = focal_from_fov(h, ang_y)
    if fx is None and fy is None:
        raise DataError(f"{where}: no focal length; expected 'fl_x' (and 'fl_y') or 'camera_angle_x'")
    fx = fx if fx is not None else fy
    fy = fy if fy is not None else fx
    cx = get("cx")
    cy = get("cy")
    cx = 0.5 * w if cx is None else cx
    cy = 0.5 * h if cy is None else cy
    if fx <= 0 or fy <= 0:
        raise DataError(f"{where}: focal length must be positive, got fx={fx}, fy={fy}")
    if (decl_w and decl_w != img_w) or (decl_h and decl_h != img_h):
        sx, sy = img_w / w, img_h / h
        fx, cx, fy, cy = fx * sx, cx * sx, fy * sy, cy * sy
        notes.add(f"declared size {int(w)}x{int(h)} differs from the images ({img_w}x{img_h}): intrinsics scaled")
    return fx, fy, cx, cy


def _read_depth_file(path: Path, factor: float | None, where: str) -> np.ndarray:
    """A z-depth map in scene units. ``.npy`` floats as stored; integer images (16-bit PNG, mm)
    times ``depth_unit_scale_factor`` (default 1e-3). NaN, inf and negative values become 0."""
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path)
        except (OSError, ValueError) as e:
            raise DataError(f"{where}: cannot read depth {path}: {e}") from None
        default = 1.0
    else:
        d = imread(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
        if d is None:
            raise DataError(f"{where}: cannot read depth image {path}")
        default = 1e-3 if np.issubdtype(d.dtype, np.integer) else 1.0
    d = np.squeeze(np.asarray(d))
    if d.ndim != 2:
        raise DataError(f"{where}: depth {path} must be a 2-D map, got shape {d.shape}")
    d = d.astype(np.float64) * (default if factor is None else factor)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d.astype(np.float32)
