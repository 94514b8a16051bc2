"""COLMAP sparse models (``.bin`` or ``.txt``), read with pycolmap: poses, intrinsics, sparse depth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from agent.camera import w2c_opencv_to_c2w_opengl
from agent.data.frames import Pixels, lens_meta, load_pixels
from agent.data.images import stack_images, unique_names
from agent.data.lens import COLMAP_LENS_MODELS, Lens, colmap_lens
from agent.data.masks import find_masks, masks_meta
from agent.data.views import DataError, Views

__all__ = ["load_colmap", "find_colmap_model"]

_PINHOLES = ("SIMPLE_PINHOLE", "PINHOLE")


def load_colmap(
    model_dir: str | Path,
    *,
    width: int | None = None,
    load_depth: bool = True,
    images_dir: str | Path | None = None,
    undistort: bool = True,
) -> Views:
    """Read a COLMAP sparse model with pycolmap: registered images, poses, intrinsics, sparse depth.

    COLMAP stores world-to-camera in the OpenCV convention (+Z forward, +Y down); the
    camera-to-world in OpenGL is ``inv([R|t]) @ diag(1, -1, -1, 1)``. Images are sorted by
    name (COLMAP's ids are arbitrary). Lens distortion (the radial, OpenCV and fisheye models,
    :data:`agent.data.lens.COLMAP_LENS_MODELS`) is undone at the images' native size; with
    ``undistort=False`` radial-tangential distortion is ignored instead (fine for near-pinhole
    cameras) and listed in ``meta['notes']``. Masks in a ``masks/`` folder beside ``images/``
    become alpha. The sparse depth of an image is the z-depth of each 3-D point it observes,
    written at the pixel of its (undistorted) keypoint (COLMAP's pixel centres are at +0.5, as
    ours), the nearest point winning; 0 elsewhere.
    """
    model_dir, rec, regs = _open_model(Path(model_dir))
    names = [im.name for im in regs]
    img_dir = _find_images_dir(model_dir, names, Path(images_dir) if images_dir is not None else None)
    masks = find_masks([img_dir / n for n in names], root=img_dir, where=f"{model_dir}: ")
    xyz_of = {pid: np.asarray(p.xyz, dtype=np.float64) for pid, p in rec.points3D.items()}

    notes: set[str] = set()
    ignored: set[str] = set()
    pixels: list[Pixels] = []
    poses, depths = [], []
    for k, im in enumerate(regs):
        cam = rec.cameras[im.camera_id]
        lens = _camera_lens(cam, im.camera_id, model_dir, undistort, notes, ignored)
        where = f"{model_dir}: image {im.name}"
        px = load_pixels(img_dir / im.name, _file_intrinsics(cam), where=where, width=width,
                         mask=masks[k] if masks else None, lens=lens)
        if pixels and pixels[0].size != px.size:
            raise DataError(f"inconsistent image sizes: {im.name} is {px.size[0]}x{px.size[1]} but {names[0]} is "
                            f"{pixels[0].size[0]}x{pixels[0].size[1]}")
        w2c = np.eye(4)
        w2c[:3, :] = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        if not np.isfinite(w2c).all():
            raise DataError(f"{where}: pose contains NaN or infinity")
        poses.append(w2c_opencv_to_c2w_opengl(w2c))
        pixels.append(px)
        if load_depth:
            depths.append(_sparse_depth(im, w2c, xyz_of, _keypoints_to_pixels(cam, px), *px.size))

    meta: dict[str, Any] = {
        "source": str(model_dir),
        "format": "colmap",
        "images_dir": str(img_dir),
        "num_points3D": len(xyz_of),
        "depth_sparse": True,
        "depth_kind": "sparse SfM points (z-depth at keypoints)",
    }
    if masks:
        meta["masks"] = masks_meta(masks)
    lens, lens_notes = lens_meta([p.undistortion for p in pixels if p.undistortion is not None], sorted(ignored))
    if lens is not None:
        meta["lens"] = lens
    meta["notes"] = sorted(notes | set(lens_notes))
    if width is not None:
        meta["width"] = width
    return Views(
        images=torch.from_numpy(stack_images([p.image for p in pixels])),
        c2w=torch.from_numpy(np.stack(poses)).float(),
        intrinsics=torch.tensor([p.intrinsics for p in pixels], dtype=torch.float32),
        names=unique_names(names),
        depth=torch.from_numpy(np.stack(depths)) if load_depth else None,
        meta=meta,
    )


def _file_intrinsics(cam: Any):
    """(W, H) of an image file -> the camera's (fx, fy, cx, cy) at that size: the files may be a
    resized copy of the images the model was made from (distortion is in normalised coordinates)."""

    def at(w0: int, h0: int) -> tuple[float, float, float, float]:
        sx, sy = w0 / cam.width, h0 / cam.height
        return (cam.focal_length_x * sx, cam.focal_length_y * sy, cam.principal_point_x * sx, cam.principal_point_y * sy)

    return at


def _keypoints_to_pixels(cam: Any, px: Pixels):
    """Keypoints [N, 2] (the model's pixels) -> their position in the prepared image (undistorted, resized)."""
    w0, h0 = px.native_size
    to_file = np.array([w0 / cam.width, h0 / cam.height])

    def convert(xy: np.ndarray) -> np.ndarray:
        uv = xy * to_file
        if px.undistortion is not None:
            uv = px.undistortion.points(uv)
        return uv * np.asarray(px.scale)

    return convert


def _open_model(model_dir: Path) -> tuple[Path, Any, list]:
    """(the model folder, the pycolmap Reconstruction, its registered images sorted by name)."""
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
    return model_dir, rec, regs


def _camera_lens(cam: Any, camera_id: int, model_dir: Path, undistort: bool, notes: set[str],
                 ignored: set[str]) -> Lens | None:
    """The lens to undo for a camera (None: a pinhole, or distortion ignored with a note)."""
    name = cam.model.name
    if name not in _PINHOLES and name not in COLMAP_LENS_MODELS:
        raise DataError(
            f"{model_dir}: camera {camera_id} uses {name}; expected one of {sorted(_PINHOLES + tuple(COLMAP_LENS_MODELS))} "
            "(undistort first, e.g. `colmap image_undistorter`)"
        )
    extra = [float(cam.params[i]) for i in cam.extra_params_idxs()]
    lens = colmap_lens(name, extra)
    if lens is None or undistort:
        return lens
    if lens.model == "fisheye":
        raise DataError(f"{model_dir}: camera {camera_id} uses {name}, a fisheye that cannot pass for a pinhole; "
                        "load with undistort=True (the default) or undistort first (`colmap image_undistorter`)")
    notes.add(f"{name} distortion ignored (camera {camera_id}: {', '.join(f'{v:.3g}' for v in extra)})")
    ignored.add(lens.name)
    return None


def _sparse_depth(im: Any, w2c: np.ndarray, xyz_of: dict, to_pixels, width: int, height: int) -> np.ndarray:
    """[height, width] float32: z-depth of the 3-D points image ``im`` observes at their keypoints' pixels.

    to_pixels: keypoints [N, 2] in the model's pixels -> pixel positions in the loaded image.
    """
    depth = np.full((height, width), np.inf)
    obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
    if obs:
        uv = to_pixels(np.array([o[0] for o in obs], dtype=np.float64))
        pts = np.stack([xyz_of[o[1]] for o in obs])
        z = pts @ w2c[2, :3] + w2c[2, 3]
        col = np.floor(uv[:, 0]).astype(np.int64)
        row = np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        np.minimum.at(depth, (row[ok], col[ok]), z[ok])
    depth[np.isinf(depth)] = 0.0
    return depth.astype(np.float32)


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
