"""COLMAP sparse models (``.bin`` or ``.txt``), read with pycolmap: poses, intrinsics, sparse depth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from agent.camera import w2c_opencv_to_c2w_opengl
from agent.data.images import read_image, resize_image, stack_images, target_size, unique_names
from agent.data.views import DataError, Views

__all__ = ["load_colmap", "find_colmap_model"]

# Camera models whose distortion we may ignore (after saying so in meta); others need undistortion.
_COLMAP_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"}


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
    model_dir, rec, regs = _open_model(Path(model_dir))
    names = [im.name for im in regs]
    img_dir = _find_images_dir(model_dir, names, Path(images_dir) if images_dir is not None else None)
    xyz_of = {pid: np.asarray(p.xyz, dtype=np.float64) for pid, p in rec.points3D.items()}

    notes: set[str] = set()
    images, poses, intrinsics, depths = [], [], [], []
    for im in regs:
        cam = rec.cameras[im.camera_id]
        _check_camera_model(cam, im.camera_id, model_dir, notes)
        where = f"{model_dir}: image {im.name}"
        img = _read_resized(img_dir / im.name, width, where)
        new_h, new_w = img.shape[:2]
        if images and images[0].shape[:2] != (new_h, new_w):
            raise DataError(f"inconsistent image sizes: {im.name} is {new_w}x{new_h} but {names[0]} is "
                            f"{images[0].shape[1]}x{images[0].shape[0]}")
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
            depths.append(_sparse_depth(im, w2c, xyz_of, sx, sy, new_w, new_h))

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
        images=torch.from_numpy(stack_images(images)),
        c2w=torch.from_numpy(np.stack(poses)).float(),
        intrinsics=torch.tensor(intrinsics, dtype=torch.float32),
        names=unique_names(names),
        depth=torch.from_numpy(np.stack(depths)) if load_depth else None,
        meta=meta,
    )


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


def _check_camera_model(cam: Any, camera_id: int, model_dir: Path, notes: set[str]) -> None:
    """Refuse models that need undistortion; note the distortion of those whose distortion is ignored."""
    model_name = cam.model.name
    if model_name not in _COLMAP_MODELS:
        raise DataError(
            f"{model_dir}: camera {camera_id} uses {model_name}; expected one of {sorted(_COLMAP_MODELS)} "
            "(undistort first, e.g. `colmap image_undistorter`)"
        )
    if model_name not in ("SIMPLE_PINHOLE", "PINHOLE"):
        extra = [float(cam.params[i]) for i in cam.extra_params_idxs()]
        if any(abs(v) > 0 for v in extra):
            notes.add(f"{model_name} distortion ignored (camera {camera_id}: {', '.join(f'{v:.3g}' for v in extra)})")


def _read_resized(path: Path, width: int | None, where: str) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{where}: image not found: {path}")
    img = read_image(path)
    h0, w0 = img.shape[:2]
    new_w, new_h = target_size(w0, h0, width, where)
    return resize_image(img, new_w, new_h)


def _sparse_depth(im: Any, w2c: np.ndarray, xyz_of: dict, sx: float, sy: float, width: int, height: int) -> np.ndarray:
    """[height, width] float32: z-depth of the 3-D points image ``im`` observes at their keypoints' pixels."""
    depth = np.full((height, width), np.inf)
    obs = [(p.xy, p.point3D_id) for p in im.points2D if p.has_point3D()]
    if obs:
        xy = np.array([o[0] for o in obs], dtype=np.float64)
        pts = np.stack([xyz_of[o[1]] for o in obs])
        z = pts @ w2c[2, :3] + w2c[2, 3]
        col = np.floor(xy[:, 0] * sx).astype(np.int64)
        row = np.floor(xy[:, 1] * sy).astype(np.int64)
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
