"""Load any supported dataset into :class:`~agent.data.views.Views`, whatever its layout.

One entry point, :func:`load_views`, looks at what it is given and picks the loader:

- ``"procedural"`` or ``"procedural:views=100,width=64,seed=0"``: the embedded scene
  (:mod:`agent.data.procedural`), so that nothing ever has to be downloaded;
- a ``transforms.json`` / ``transforms_train.json`` (or a folder holding one) in the Blender,
  nerfstudio or instant-ngp conventions;
- a COLMAP sparse model (``sparse/0/`` or a folder with ``cameras``/``images``/``points3D`` as
  ``.bin`` or ``.txt``), read with pycolmap;
- a folder of images only, handed to ``agent.data.sfm.run_sfm`` when that module is installed.

Every loader returns the conventions of :mod:`agent.data.views` (OpenGL camera-to-world,
per-view ``fx, fy, cx, cy`` with the pixel centre at ``u + 0.5``, z-depth with 0 = unknown,
straight RGBA kept), and every failure the user can fix is a :class:`DataError` that names the
file and says what was expected.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import math
import typing
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from agent.camera import focal_from_fov, w2c_opencv_to_c2w_opengl
from agent.data.views import DataError, Views

__all__ = [
    "load_views",
    "load_transforms",
    "load_colmap",
    "find_colmap_model",
    "parse_procedural_spec",
    "resize_image",
    "resize_depth",
    "resize_views",
    "IMAGE_EXTENSIONS",
    "EXPECTED_LAYOUTS",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".tif", ".tiff", ".bmp", ".webp")
EXPECTED_LAYOUTS = (
    "expected transforms.json, transforms_train.json, a COLMAP model (sparse/0/ or cameras/images/points3D "
    ".bin|.txt), a folder of images, or 'procedural[:views=100,width=64,seed=0]'"
)

# Camera models whose distortion we may ignore (after saying so in meta); others need undistortion.
_COLMAP_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"}
_UNSUPPORTED_NS_MODELS = {"OPENCV_FISHEYE", "FISHEYE", "EQUIRECTANGULAR", "FOV", "THIN_PRISM_FISHEYE"}
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


# --------------------------------------------------------------------------------------------
# Dispatcher
# --------------------------------------------------------------------------------------------


def load_views(
    source: str | Path,
    *,
    width: int | None = None,
    load_depth: bool = True,
    images_dir: str | Path | None = None,
    sfm_cache_dir: str | Path | None = None,
) -> Views:
    """Load ``source`` (a path or ``procedural[:k=v,...]``) as :class:`Views`.

    width: target image width in pixels (downscale only, area interpolation; the height follows
    the aspect ratio and intrinsics are scaled with the image). ``None`` keeps the native size.
    load_depth: read depth maps when the dataset has them (transforms.json ``depth_file_path``;
    COLMAP sparse depth from the 3-D points).
    images_dir: where a COLMAP model's images are, when not next to the model.
    sfm_cache_dir: where SfM of an images-only folder keeps its result (default: not cached).
    """
    if width is not None and (not isinstance(width, int) or width < 1):
        raise DataError(f"width must be a positive integer, got {width!r}")
    text = str(source)
    if (text == "procedural" or text.startswith("procedural:")) and not Path(text).exists():
        from agent.data.procedural import procedural_views

        cfg = parse_procedural_spec(text, width=width)
        return procedural_views(cfg)

    path = Path(source).expanduser()
    if not path.exists():
        raise DataError(f"{path}: no such file or folder; {EXPECTED_LAYOUTS}")
    if path.is_file():
        if path.suffix.lower() == ".json":
            return load_transforms(path, width=width, load_depth=load_depth)
        if path.stem in ("cameras", "images", "points3D") and path.suffix in (".bin", ".txt"):
            return load_colmap(path.parent, width=width, load_depth=load_depth, images_dir=images_dir)
        raise DataError(f"{path}: not a dataset file; {EXPECTED_LAYOUTS}")

    for name in ("transforms.json", "transforms_train.json"):
        if (path / name).is_file():
            return load_transforms(path / name, width=width, load_depth=load_depth)
    model = find_colmap_model(path)
    if model is not None:
        return load_colmap(model, width=width, load_depth=load_depth, images_dir=images_dir)
    images = _list_images(path) or _list_images(path / "images")
    if images:
        return _load_images_only(path, images, width=width, cache_dir=sfm_cache_dir)
    if (path / "split.json").is_file():
        robots = sorted(p.name for p in path.glob("robot*") if p.is_dir())
        raise DataError(f"{path} is the output of `dinerf-agent split`; load one of its folders: {robots + ['eval']}")
    found = sorted(p.name + ("/" if p.is_dir() else "") for p in path.iterdir())[:12]
    raise DataError(f"{path}: no known dataset layout; {EXPECTED_LAYOUTS}. Found: {found or 'an empty folder'}")


def parse_procedural_spec(text: str, width: int | None = None):
    """``procedural:views=100,width=64,seed=0`` -> ``ProceduralConfig``.

    Keys are the fields of ``ProceduralConfig`` (``views`` is short for ``num_views``); values
    are numbers, or ``a/b`` for a pair such as ``elevation_deg=10/60``. A width without a height
    keeps the aspect ratio; ``width`` given to :func:`load_views` wins over the spec.
    """
    from agent.data.procedural import ProceduralConfig

    fields = {f.name: f for f in dataclasses.fields(ProceduralConfig)}
    hints = typing.get_type_hints(ProceduralConfig)
    aliases = {"views": "num_views", "n": "num_views", "fov": "fov_deg", "elevation": "elevation_deg"}
    kwargs: dict[str, Any] = {}
    _, _, body = text.partition(":")
    for item in filter(None, (s.strip() for s in body.split(","))):
        key, eq, value = item.partition("=")
        key = aliases.get(key.strip(), key.strip())
        if not eq or key not in fields:
            raise DataError(
                f"procedural spec {text!r}: bad item {item!r}; expected key=value with keys "
                f"{sorted(set(fields) | {'views'})}"
            )
        kind = hints[key]
        try:
            if kind is int:
                kwargs[key] = int(value)
            elif kind is float:
                kwargs[key] = float(value)
            else:  # a pair of floats
                lo, hi = value.split("/")
                kwargs[key] = (float(lo), float(hi))
        except ValueError:
            raise DataError(f"procedural spec {text!r}: cannot read {key}={value!r}") from None
    if "width" in kwargs and "height" not in kwargs:  # a width alone keeps the default aspect ratio
        default = ProceduralConfig()
        kwargs["height"] = max(1, round(default.height * kwargs["width"] / default.width))
    cfg = ProceduralConfig(**kwargs)
    if width is not None and width != cfg.width:
        height = max(1, round(cfg.height * width / cfg.width))
        cfg = dataclasses.replace(cfg, width=width, height=height)
    return cfg


# --------------------------------------------------------------------------------------------
# Image and depth helpers
# --------------------------------------------------------------------------------------------


def _read_image(path: Path) -> np.ndarray:
    """Read an image as float32 [H, W, 3|4] in [0, 1], RGB(A) channel order."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: cannot be read as an image")
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype)
    if scale is None and not np.issubdtype(img.dtype, np.floating):
        raise DataError(f"{path}: unsupported pixel type {img.dtype}")
    img = img.astype(np.float32) / (scale or 1.0)
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
    return np.ascontiguousarray(np.clip(img, 0.0, 1.0))


def _target_size(width: int, height: int, target_width: int | None, where: str) -> tuple[int, int]:
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
    new_w, new_h = _target_size(views.width, views.height, width, "resize")
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


def _list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix in IMAGE_EXTENSIONS)


def _unique_names(paths: list[str]) -> list[str]:
    """File stems when they are unique, else the relative paths with '/' turned into '_'."""
    stems = [Path(p).stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    flat = [str(Path(p).with_suffix("")).lstrip("./").replace("/", "_").replace("\\", "_") for p in paths]
    if len(set(flat)) != len(flat):
        raise DataError(f"duplicate image names: {sorted({n for n in flat if flat.count(n) > 1})[:5]}")
    return flat


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


# --------------------------------------------------------------------------------------------
# transforms.json (Blender / nerfstudio / instant-ngp)
# --------------------------------------------------------------------------------------------


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


def _frame_intrinsics(top: dict, frame: dict, img_w: int, img_h: int, where: str, notes: set[str]) -> tuple[float, ...]:
    """(fx, fy, cx, cy) at the image's native size; per-frame keys override top-level ones.

    Precedence follows the formats: ``fl_x``/``fl_y`` (nerfstudio, instant-ngp) over
    ``camera_angle_x``/``camera_angle_y`` (Blender); a missing ``fl_y`` means square pixels; a
    missing ``cx``/``cy`` means the image centre. When the declared ``w``/``h`` differ from the
    image on disk (a downscaled copy of the images), the intrinsics are scaled to the image.
    """

    def get(key: str) -> float | None:
        v = _num(frame, key, where)
        return v if v is not None else _num(top, key, where)

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
    for key in _DISTORTION_KEYS:
        v = get(key)
        if v:
            notes.add("lens distortion ignored (" + ", ".join(k for k in _DISTORTION_KEYS if get(k)) + ")")
            break
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
        d = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
        if d is None:
            raise DataError(f"{where}: cannot read depth image {path}")
        default = 1e-3 if np.issubdtype(d.dtype, np.integer) else 1.0
    d = np.squeeze(np.asarray(d))
    if d.ndim != 2:
        raise DataError(f"{where}: depth {path} must be a 2-D map, got shape {d.shape}")
    d = d.astype(np.float64) * (default if factor is None else factor)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d.astype(np.float32)


def load_transforms(json_path: str | Path, *, width: int | None = None, load_depth: bool = True) -> Views:
    """Read a Blender / nerfstudio / instant-ngp ``transforms*.json``.

    Poses are OpenGL camera-to-world in all three formats and are kept in the file's units
    (instant-ngp's ``scale``/``offset``/``aabb_scale`` are rendering hints of that program and
    are only copied into ``meta``). ``file_path`` is relative to the json, with or without its
    extension. Images keep their alpha; frames without alpha get alpha 1 when others have it.
    """
    json_path = Path(json_path)
    try:
        top = json.loads(json_path.read_text())
    except FileNotFoundError:
        raise DataError(f"{json_path}: no such file; {EXPECTED_LAYOUTS}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{json_path}: not valid JSON: {e}") from None
    if not isinstance(top, dict):
        raise DataError(f"{json_path}: expected a JSON object with a 'frames' list")
    frames = top.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{json_path}: no frames; expected a non-empty 'frames' list of {{file_path, transform_matrix}}")
    model = str(top.get("camera_model", "")).upper()
    if model in _UNSUPPORTED_NS_MODELS:
        raise DataError(f"{json_path}: camera_model {model} is not supported; expected a pinhole model (PINHOLE, OPENCV)")

    base = json_path.parent
    notes: set[str] = set()
    dinerf = top["dinerf"] if isinstance(top.get("dinerf"), dict) else {}  # written by `dinerf-agent split`
    # sparse depth (SfM points) must be resized point by point, not by nearest neighbour
    sparse_depth = bool(dinerf.get("depth_sparse", False))
    factor = _num(top, "depth_unit_scale_factor", str(json_path))
    rel_paths: list[str] = []
    images: list[np.ndarray] = []
    depths: list[np.ndarray | None] = []
    poses: list[np.ndarray] = []
    intrinsics: list[tuple[float, ...]] = []
    size: tuple[int, int] | None = None
    first_name = ""
    for i, frame in enumerate(frames):
        where = f"{json_path.name}: frame {i}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise DataError(f"{where}: expected an object with 'file_path' and 'transform_matrix'")
        fp = str(frame["file_path"])
        where = f"{json_path.name}: frame {i} ({fp})"
        img_path = _resolve_image(base, fp)
        if img_path is None:
            raise DataError(f"{where}: image not found: {base / fp} (also tried .png/.jpg/.jpeg)")
        pose = _check_pose(frame["transform_matrix"], where)
        img = _read_image(img_path)
        h0, w0 = img.shape[:2]
        fx, fy, cx, cy = _frame_intrinsics(top, frame, w0, h0, where, notes)
        new_w, new_h = _target_size(w0, h0, width, where)
        sx, sy = new_w / w0, new_h / h0
        img = resize_image(img, new_w, new_h)
        if size is None:
            size, first_name = (new_w, new_h), fp
        elif size != (new_w, new_h):
            raise DataError(
                f"inconsistent image sizes: {fp} is {new_w}x{new_h} but {first_name} is {size[0]}x{size[1]}"
                + ("" if width is None else f" (after resizing to width {width})")
            )
        depth = None
        dfp = frame.get("depth_file_path")
        if load_depth and dfp:
            dpath = base / str(dfp)
            if not dpath.is_file():
                raise DataError(f"{where}: depth file not found: {dpath}")
            depth = resize_depth(_read_depth_file(dpath, factor, where), new_w, new_h, sparse=sparse_depth)
        rel_paths.append(fp)
        images.append(img)
        depths.append(depth)
        poses.append(pose)
        intrinsics.append((fx * sx, fy * sy, cx * sx, cy * sy))

    channels = max(im.shape[2] for im in images)
    if channels == 4:
        images = [im if im.shape[2] == 4 else np.concatenate([im, np.ones_like(im[:, :, :1])], 2) for im in images]
    depth_t = None
    if any(d is not None for d in depths):
        assert size is not None
        depth_t = torch.from_numpy(
            np.stack([d if d is not None else np.zeros((size[1], size[0]), np.float32) for d in depths])
        )
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
    return Views(
        images=torch.from_numpy(np.stack(images)),
        c2w=torch.from_numpy(np.stack(poses)).float(),
        intrinsics=torch.tensor(intrinsics, dtype=torch.float32),
        names=_unique_names(rel_paths),
        depth=depth_t,
        meta=meta,
    )


def _transforms_flavour(top: dict, frames: list) -> str:
    if "fl_x" in top or any(isinstance(f, dict) and "fl_x" in f for f in frames):
        return "nerfstudio" if "camera_model" in top else "instant-ngp"
    return "blender"


# --------------------------------------------------------------------------------------------
# COLMAP sparse model
# --------------------------------------------------------------------------------------------


def _is_colmap_model(folder: Path) -> bool:
    return all(
        (folder / f"{n}.bin").is_file() or (folder / f"{n}.txt").is_file() for n in ("cameras", "images", "points3D")
    )


def find_colmap_model(folder: Path) -> Path | None:
    """The COLMAP model folder under ``folder`` (itself, sparse/0, sparse, colmap/sparse/0)."""
    for cand in (folder, folder / "sparse" / "0", folder / "sparse", folder / "colmap" / "sparse" / "0"):
        if cand.is_dir() and _is_colmap_model(cand):
            return cand
    return None


def _find_images_dir(model: Path, names: list[str], images_dir: Path | None) -> Path:
    cands = [images_dir] if images_dir is not None else []
    # dataset/sparse/0 -> dataset/images; dataset/sparse -> dataset/images; model/images
    cands += [model.parent.parent / "images", model.parent / "images", model / "images", model.parent.parent, model.parent]
    for c in cands:
        if c is not None and c.is_dir() and names and (c / names[0]).is_file():
            return c
    tried = ", ".join(str(c) for c in cands if c is not None)
    raise DataError(f"{model}: images of the COLMAP model not found (looked for {names[0]!r} in {tried}); pass images_dir")


def load_colmap(
    model_dir: str | Path,
    *,
    width: int | None = None,
    load_depth: bool = True,
    images_dir: str | Path | None = None,
) -> Views:
    """Read a COLMAP sparse model with pycolmap: registered images, poses, intrinsics, sparse depth.

    COLMAP stores world-to-camera in the OpenCV convention (+Z forward, +Y down); the
    camera-to-world in OpenGL is ``inv([R|t]) @ diag(1, -1, -1, 1)``. Images are sorted by
    name (COLMAP's ids are arbitrary). Radial/tangential distortion of the supported models is
    ignored (fine for the small distortion of undistorted or near-pinhole cameras) and listed in
    ``meta['notes']``. The sparse depth of an image is the z-depth of each 3-D point it observes,
    written at the pixel of its keypoint (COLMAP's pixel centres are at +0.5, as ours), the
    nearest point winning; 0 elsewhere.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir() or not _is_colmap_model(model_dir):
        found = find_colmap_model(model_dir) if model_dir.is_dir() else None
        if found is None:
            raise DataError(f"{model_dir}: not a COLMAP model; expected cameras, images and points3D as .bin or .txt")
        model_dir = found
    import pycolmap

    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on malformed files
        raise DataError(f"{model_dir}: cannot read the COLMAP model: {e}") from None
    regs = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not regs:
        raise DataError(f"{model_dir}: the COLMAP model has no registered images")
    names = [im.name for im in regs]
    img_dir = _find_images_dir(model_dir, names, Path(images_dir) if images_dir is not None else None)
    xyz_of = {pid: np.asarray(p.xyz, dtype=np.float64) for pid, p in rec.points3D.items()}

    notes: set[str] = set()
    images, poses, intrinsics, depths = [], [], [], []
    size: tuple[int, int] | None = None
    for im in regs:
        cam = rec.cameras[im.camera_id]
        model_name = cam.model.name
        if model_name not in _COLMAP_MODELS:
            raise DataError(
                f"{model_dir}: camera {im.camera_id} uses {model_name}; expected one of {sorted(_COLMAP_MODELS)} "
                "(undistort first, e.g. `colmap image_undistorter`)"
            )
        if model_name not in ("SIMPLE_PINHOLE", "PINHOLE"):
            extra = [float(cam.params[i]) for i in cam.extra_params_idxs()]
            if any(abs(v) > 0 for v in extra):
                notes.add(f"{model_name} distortion ignored (camera {im.camera_id}: {', '.join(f'{v:.3g}' for v in extra)})")
        where = f"{model_dir}: image {im.name}"
        path = img_dir / im.name
        if not path.is_file():
            raise DataError(f"{where}: image not found: {path}")
        img = _read_image(path)
        h0, w0 = img.shape[:2]
        new_w, new_h = _target_size(w0, h0, width, where)
        img = resize_image(img, new_w, new_h)
        if size is None:
            size = (new_w, new_h)
        elif size != (new_w, new_h):
            raise DataError(f"inconsistent image sizes: {im.name} is {new_w}x{new_h} but {names[0]} is {size[0]}x{size[1]}")
        # intrinsics are for cam.width x cam.height; the files may be a resized copy
        sx, sy = new_w / cam.width, new_h / cam.height
        intrinsics.append(
            (cam.focal_length_x * sx, cam.focal_length_y * sy, cam.principal_point_x * sx, cam.principal_point_y * sy)
        )
        w2c = np.eye(4)
        w2c[:3, :] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        if not np.isfinite(w2c).all():
            raise DataError(f"{where}: pose contains NaN or infinity")
        poses.append(w2c_opencv_to_c2w_opengl(w2c))
        images.append(img)
        if load_depth:
            depth = np.full((new_h, new_w), np.inf)
            obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
            if obs:
                xy = np.array([o[0] for o in obs], dtype=np.float64)
                pts = np.stack([xyz_of[o[1]] for o in obs])
                z = pts @ w2c[2, :3] + w2c[2, 3]
                col = np.floor(xy[:, 0] * sx).astype(np.int64)
                row = np.floor(xy[:, 1] * sy).astype(np.int64)
                ok = (z > 0) & (col >= 0) & (col < new_w) & (row >= 0) & (row < new_h)
                np.minimum.at(depth, (row[ok], col[ok]), z[ok])
            depth[np.isinf(depth)] = 0.0
            depths.append(depth.astype(np.float32))

    channels = max(im.shape[2] for im in images)
    if channels == 4:
        images = [im if im.shape[2] == 4 else np.concatenate([im, np.ones_like(im[:, :, :1])], 2) for im in images]
    meta: dict[str, Any] = {
        "source": str(model_dir),
        "format": "colmap",
        "images_dir": str(img_dir),
        "notes": sorted(notes),
        "num_points3D": len(xyz_of),
        "depth_sparse": True,
        "depth_kind": "sparse SfM points (z-depth at keypoints)",
    }
    if width is not None:
        meta["width"] = width
    return Views(
        images=torch.from_numpy(np.stack(images)),
        c2w=torch.from_numpy(np.stack(poses)).float(),
        intrinsics=torch.tensor(intrinsics, dtype=torch.float32),
        names=_unique_names(names),
        depth=torch.from_numpy(np.stack(depths)) if load_depth else None,
        meta=meta,
    )


# --------------------------------------------------------------------------------------------
# Images only -> SfM (agent.data.sfm, written separately)
# --------------------------------------------------------------------------------------------


def _load_images_only(folder: Path, images: list[Path], *, width: int | None, cache_dir: str | Path | None = None) -> Views:
    """Hand a folder of unposed images to ``agent.data.sfm.run_sfm``, imported lazily.

    The SfM module may return :class:`Views` or the path of a COLMAP model it wrote; both are
    accepted. Only the keyword arguments its signature declares are passed.
    """
    try:  # import_module consults sys.modules first, so tests can simulate presence and absence
        sfm = importlib.import_module("agent.data.sfm")
    except ImportError as e:
        raise DataError(
            f"{folder}: holds {len(images)} images but no poses, and SfM support (agent.data.sfm) is not "
            f"installed ({e}); {EXPECTED_LAYOUTS}"
        ) from None
    run = getattr(sfm, "run_sfm", None)
    if run is None:
        raise DataError(f"{folder}: holds only images, and agent.data.sfm has no run_sfm(); SfM support is not installed")
    params = inspect.signature(run).parameters
    kwargs: dict[str, Any] = {"width": width} if "width" in params else {}
    if cache_dir is not None and "cache_dir" in params:
        kwargs["cache_dir"] = cache_dir
        if "keep_frame" in params:  # the run's own SfM is the robot's frame: never silently redone
            kwargs["keep_frame"] = True
    result = run(folder, **kwargs)
    if isinstance(result, Views):
        return resize_views(result, width) if width is not None and width != result.width else result
    if isinstance(result, (str, Path)):
        return load_colmap(Path(result), width=width)
    raise DataError(f"{folder}: run_sfm returned {type(result).__name__}; expected Views or a COLMAP model path")
