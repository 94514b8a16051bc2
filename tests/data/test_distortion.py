"""Lens distortion: the model agrees with OpenCV, renders move pixels as it says, folders carry it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from agent.camera import DISTORTION_KEYS, OPENCV_FROM_OPENGL, camera_directions, distort, distortion_coeffs, undistort

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
