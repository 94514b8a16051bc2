"""Lens distortion: the model agrees with OpenCV, renders move pixels as it says, folders carry it."""

from __future__ import annotations

import json

import cv2
import numpy as np
import torch

from agent.camera import (
    DISTORTION_KEYS,
    OPENCV_FROM_OPENGL,
    camera_directions,
    distort,
    distortion_coeffs,
    undistort,
    unproject_depth,
)
from agent.data.folder import write_views_folder
from agent.data.procedural import ProceduralConfig, procedural_views, render_procedural, scene_sdf
from agent.data.split import SplitConfig, split_views, write_split
from agent.geometry import look_at

LENS = (0.06, -0.02, 0.003, -0.002)  # k1, k2, p1, p2


def test_distort_is_opencvs_model_and_undistort_inverts_it():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.6, 0.6, (500, 2))
    xd, yd = distort(xy[:, 0], xy[:, 1], LENS)
    proj, _ = cv2.projectPoints(np.c_[xy, np.ones(500)], np.zeros(3), np.zeros(3), np.eye(3), np.array(LENS))
    assert np.allclose(proj[:, 0], np.c_[xd, yd], atol=1e-12)
    x, y = undistort(xd, yd, LENS)
    assert np.allclose(np.c_[x, y], xy, atol=1e-12)
    xt, yt = undistort(torch.from_numpy(xd), torch.from_numpy(yd), LENS)  # torch too, same formula
    assert torch.allclose(torch.stack([xt, yt], -1), torch.from_numpy(xy), atol=1e-12)


def test_directions_through_distorted_pixels_project_back_with_opencv():
    k = np.array([60.0, 58.0, 31.0, 23.5])
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(48) + 0.5)
    dirs = camera_directions(k, u, v, LENS).reshape(-1, 3)  # OpenGL camera frame, z = -1
    cam_cv = dirs @ OPENCV_FROM_OPENGL[:3, :3]  # OpenCV camera frame: +Y down, +Z forward
    kk = np.array([[k[0], 0, k[2] - 0.5], [0, k[1], k[3] - 0.5], [0, 0, 1]])  # OpenCV pixel centres at i
    proj, _ = cv2.projectPoints(cam_cv, np.zeros(3), np.zeros(3), kk, np.array(LENS))
    assert np.abs(proj[:, 0] + 0.5 - np.c_[u.ravel(), v.ravel()]).max() < 1e-9
    assert np.array_equal(camera_directions(k, u, v), camera_directions(k, u, v, None))


def test_distortion_coefficients_from_named_fields():
    assert DISTORTION_KEYS == ("k1", "k2", "p1", "p2")
    assert distortion_coeffs({"k1": 0.1, "p2": 0.01}) == (0.1, 0.0, 0.0, 0.01)
    assert distortion_coeffs({"k1": 0.0}) is None and distortion_coeffs(None) is None


def _world_to_opencv_camera(c2w: torch.Tensor, points: torch.Tensor) -> np.ndarray:
    """World points [N, 3] -> the OpenCV camera frame of the OpenGL camera c2w [4, 4]."""
    w2c = torch.linalg.inv(c2w.double())
    cam = points.double() @ w2c[:3, :3].T + w2c[:3, 3]
    return (cam.numpy() @ OPENCV_FROM_OPENGL[:3, :3]).astype(np.float64)


def test_a_rendered_point_sits_where_opencv_projects_it():
    """Surface points of a pinhole render, projected by cv2.projectPoints through the lens, are seen
    by the distorting render exactly there (to 1e-3 px): one 1x1 render per point whose pixel centre
    is the projected position (shifting cx, cy by the same amount moves the grid, not the lens)."""
    c2w = look_at(torch.tensor([3.0, -2.0, 2.0]), torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])).float()
    w, h = 64, 48
    k = torch.tensor([50.0, 50.0, 32.0, 24.0])
    _, depth = render_procedural(c2w[None], k[None], w, h, room=True)
    rows, cols = torch.meshgrid(torch.arange(2, h, 5), torch.arange(2, w, 5), indexing="ij")
    sample = torch.zeros_like(depth[0])
    sample[rows, cols] = depth[0, rows, cols]
    points = unproject_depth(sample, k, c2w)  # [N, 3] world points that the pinhole render sees
    kk = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    cam_cv = _world_to_opencv_camera(c2w, points)
    uv = cv2.projectPoints(cam_cv, np.zeros(3), np.zeros(3), kk, np.array(LENS))[0][:, 0] + 0.5  # our pixel coords
    inside = (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)
    uv, cam_cv = uv[inside], cam_cv[inside]
    pinhole = cam_cv[:, :2] / cam_cv[:, 2:] * 50.0 + [32.0, 24.0]
    assert np.abs(uv - pinhole).max() > 0.5, "the lens moves the border by most of a pixel"
    one_px = k.double().repeat(len(uv), 1)
    one_px[:, 2:] += 0.5 - torch.from_numpy(uv)  # the 1x1 image's pixel centre lands on uv
    _, z = render_procedural(c2w.double().repeat(len(uv), 1, 1), one_px, 1, 1, room=True, distortion=LENS)
    # the ray through uv reaches the very point: its z-depth agrees to 1e-4 units, i.e. 1e-3 px at 5 units
    assert np.abs(z[:, 0, 0].numpy() - cam_cv[:, 2]).max() < 1e-4


def test_procedural_lens_views_carry_their_distortion():
    cfg = ProceduralConfig(num_views=3, width=32, height=32, supersample=1, room=True, k1=0.06, p1=0.002)
    v = procedural_views(cfg)
    assert v.meta["distortion"] == {"k1": 0.06, "k2": 0.0, "p1": 0.002, "p2": 0.0}
    pinhole = procedural_views(ProceduralConfig(**{**vars(cfg), "k1": 0.0, "p1": 0.0}))
    assert "distortion" not in pinhole.meta and not torch.equal(v.images, pinhole.images)
    centre = (slice(15, 17), slice(15, 17))  # the lens barely moves the pixels round the optical axis
    assert (v.images[:, centre[0], centre[1]] - pinhole.images[:, centre[0], centre[1]]).abs().max() < 0.05
    for i in range(len(v)):  # depth is along each pixel's true ray
        pts = unproject_depth(v.depth[i], v.intrinsics[i], v.c2w[i], cfg.distortion)
        assert float(scene_sdf(pts, room=True).abs().max()) < 1e-4


def test_folders_carry_the_lens_in_nerfstudio_fields(tmp_path):
    v = procedural_views(ProceduralConfig(num_views=12, width=16, height=12, k1=0.06, k2=0.01, p2=-0.001, room=True))
    top = write_views_folder(v, tmp_path / "one")
    assert json.loads((tmp_path / "one/transforms.json").read_text()) == top
    assert top["camera_model"] == "OPENCV"
    assert {k: top[k] for k in DISTORTION_KEYS} == {"k1": 0.06, "k2": 0.01, "p1": 0.0, "p2": -0.001}
    assert {"fl_x", "fl_y", "cx", "cy", "w", "h"} <= set(top) and (top["w"], top["h"]) == (16, 12)
    plain = write_views_folder(procedural_views(ProceduralConfig(num_views=2, width=8)), tmp_path / "plain")
    assert plain["camera_model"] == "PINHOLE" and not set(DISTORTION_KEYS) & set(plain)
    # every folder of a split records the lens of its images
    write_split(split_views(v, SplitConfig(robots=2, test_every=4, frame="random")), tmp_path / "split")
    for folder in ("robot1", "robot2", "eval"):
        spec = json.loads((tmp_path / "split" / folder / "transforms.json").read_text())
        assert spec["camera_model"] == "OPENCV" and spec["k1"] == 0.06 and spec["p2"] == -0.001, folder
