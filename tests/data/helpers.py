"""Tiny hand-made datasets for the loader tests: written in the test, so every number is known."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared/data"
LEGO = SHARED_DATA / "nerf_synthetic/lego"


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
