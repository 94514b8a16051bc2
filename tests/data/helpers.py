"""Tiny hand-made datasets for the loader tests: written in the test, so every number is known."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np

# ../shared/data beside the repository; DINERF_SHARED_DATA points elsewhere (e.g. from a git worktree)
SHARED_DATA = Path(os.environ.get("DINERF_SHARED_DATA") or Path(__file__).resolve().parents[2].parent / "shared/data")
LEGO = SHARED_DATA / "nerf_synthetic/lego"
MARYROSE = SHARED_DATA / "maryrose"


def write_png(path: Path, img: np.ndarray) -> None:
    """img: [H, W, 3|4] float in [0, 1] (RGB order) -> 8-bit PNG; or uint16 [H, W] as is."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.dtype == np.uint16:
        assert cv2.imwrite(str(path), img)
        return
    q = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    q = q[:, :, [2, 1, 0, 3]] if q.shape[2] == 4 else q[:, :, ::-1]
    assert cv2.imwrite(str(path), np.ascontiguousarray(q))


def pose(angle_deg: float, t: tuple[float, float, float]) -> list[list[float]]:
    """A camera-to-world with a rotation about z: any valid pose will do."""
    a = np.radians(angle_deg)
    m = np.eye(4)
    m[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    m[:3, 3] = t
    return m.tolist()


def random_rgba(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 1, (h, w, 4))
    img[..., 3] = np.round(img[..., 3])  # exact 0/1 alpha survives 8-bit round trips
    return img


def write_json(path: Path, data: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def blender_dataset(root: Path, w: int = 16, h: int = 12, n: int = 3, **top) -> Path:
    """Blender layout: transforms_train.json, camera_angle_x, './train/r_i' without extension."""
    frames = []
    for i in range(n):
        write_png(root / "train" / f"r_{i}.png", random_rgba(h, w, i))
        frames.append({"file_path": f"./train/r_{i}", "rotation": 0.1, "transform_matrix": pose(30 * i, (i, 1, 4))})
    return write_json(root / "transforms_train.json", {"camera_angle_x": 0.8, **top, "frames": frames})


def _qvec(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix -> COLMAP quaternion (w, x, y, z)."""
    w = math.sqrt(max(0.0, 1 + np.trace(rot))) / 2
    x = (rot[2, 1] - rot[1, 2]) / (4 * w)
    y = (rot[0, 2] - rot[2, 0]) / (4 * w)
    z = (rot[1, 0] - rot[0, 1]) / (4 * w)
    return np.array([w, x, y, z])


def colmap_dataset(root, model="PINHOLE", params=(50.0, 52.0, 20.5, 14.5), w=40, h=30, distorted_keypoints=False):
    """A text model with 2 images and 6 points whose keypoints are their exact projections.

    distorted_keypoints: project through the camera model with pycolmap (lens distortion
    included) instead of the pinhole part of its parameters.
    """
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (6, 3))
    fx, fy, cx, cy = (params[0], params[0], params[1], params[2]) if model.startswith("SIMPLE") else params[:4]
    w2cs = []
    for i, angle in enumerate((0.0, 0.3)):
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        w2cs.append((rot, np.array([0.1 * i, -0.05, 3.0])))
    lines, tracks = [], {j: [] for j in range(len(points))}
    keypoints = []
    for i, (rot, t) in enumerate(w2cs):
        q = _qvec(rot)
        lines.append(f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 img{i}.png")
        cam = points @ rot.T + t
        uv = np.stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy], -1)
        if distorted_keypoints:
            import pycolmap

            uv = pycolmap.Camera(model=model, width=w, height=h, params=list(params)).img_from_cam(cam)
        keypoints.append((uv, cam[:, 2]))
        lines.append(" ".join(f"{u} {v} {j + 1}" for j, (u, v) in enumerate(uv)) + " 3.0 4.0 -1")
        for j in range(len(points)):
            tracks[j].append(f"{i + 1} {j}")
        write_png(root / "images" / f"img{i}.png", random_rgba(h, w, i)[..., :3])
    model_dir = root / "sparse" / "0"
    model_dir.mkdir(parents=True)
    (model_dir / "cameras.txt").write_text(f"1 {model} {w} {h} {' '.join(map(str, params))}\n")
    (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    (model_dir / "points3D.txt").write_text(
        "".join(f"{j + 1} {p[0]} {p[1]} {p[2]} 255 0 0 0.1 {' '.join(tracks[j])}\n" for j, p in enumerate(points))
    )
    return points, keypoints, (fx, fy, cx, cy)
