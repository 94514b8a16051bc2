"""Lens distortion undone at load time: distorted images of a known pattern come back as pinhole images.

The pattern is a grid of Gaussian dots on a plane facing the camera, evaluated at the point each
distorted pixel sees (the lens model's own inverse: OpenCV's for transforms.json, pycolmap's for
COLMAP, so the latter checks our reading of COLMAP's parameters independently). Through a pinhole
such a dot is a Gaussian centred on the projection of its centre; the dots of the loaded image
must sit there, within a fraction of a pixel.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from agent.camera import opencv_camera_matrix, pixel_to_opencv
from agent.data.loaders import load_views

from .helpers import colmap_dataset, pose, write_json, write_png

W, H = 96, 72
K = (70.0, 72.0, 47.3, 36.8)  # fx, fy, cx, cy: the principal point off-centre on purpose
SIGMA_PX = 1.6
SPACING_PX = 15
CRIT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 300, 1e-14)


def _dots() -> np.ndarray:
    """Dot centres [N, 2] in normalised coordinates (x right, y down, on the plane z = 1)."""
    us = np.arange(-3, 4) * SPACING_PX / K[0]
    vs = np.arange(-2, 3) * SPACING_PX / K[1]
    return np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)


def _pattern(xy: np.ndarray) -> np.ndarray:
    """Intensity at normalised points [..., 2]: grey 0.2 and white Gaussian dots."""
    s = SIGMA_PX / K[0]
    d2 = ((xy[..., None, :] - _dots()) ** 2).sum(-1)
    return 0.2 + 0.75 * np.exp(-d2 / (2 * s * s)).sum(-1)


def _render(to_normalised) -> np.ndarray:
    """The distorted image [H, W, 3]: the pattern at the point each pixel centre sees."""
    cols, rows = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xy = to_normalised(np.stack([cols, rows], -1).reshape(-1, 2)).reshape(H, W, 2)
    assert np.isfinite(xy).all(), "the lens must map every pixel of the test image"
    return np.repeat(_pattern(xy)[:, :, None], 3, axis=2)


def _opencv_inverse(coeffs, fisheye=False):
    """Pixel positions (our convention) -> normalised coordinates through OpenCV's lens model."""
    k, d = opencv_camera_matrix(K), np.array(coeffs, dtype=np.float64)

    def inv(uv):
        src = pixel_to_opencv(uv).reshape(-1, 1, 2)
        if fisheye:
            return cv2.fisheye.undistortPoints(src, k, d, criteria=CRIT).reshape(-1, 2)
        return cv2.undistortPoints(src, k, d, criteria=CRIT).reshape(-1, 2)

    return inv


def dot_errors(img: np.ndarray, intrinsics) -> np.ndarray:
    """Distance [N] (pixels) between each dot's centroid in a pinhole image and its projection."""
    fx, fy, cx, cy = (float(x) for x in intrinsics)
    h, w = img.shape[:2]
    sigma = SIGMA_PX * fx / K[0]
    r = int(np.ceil(4 * sigma))
    lum = img[..., 0].astype(np.float64) - 0.2
    errs = []
    for x, y in _dots():
        u, v = fx * x + cx, fy * y + cy
        c0, r0 = int(np.floor(u)) - r, int(np.floor(v)) - r
        if c0 < 0 or r0 < 0 or c0 + 2 * r + 1 > w or r0 + 2 * r + 1 > h:
            continue  # cropped away by the pinhole camera, or too close to its edge
        win = lum[r0:r0 + 2 * r + 1, c0:c0 + 2 * r + 1]
        cols, rows = np.meshgrid(np.arange(c0, c0 + 2 * r + 1) + 0.5, np.arange(r0, r0 + 2 * r + 1) + 0.5)
        centroid = np.array([(win * cols).sum(), (win * rows).sum()]) / win.sum()
        errs.append(np.hypot(*(centroid - (u, v))))
    return np.array(errs)


def _nerfstudio(root, camera_model: str, coeffs: dict, img: np.ndarray, **frame_extra):
    write_png(root / "images/a.png", img)
    frame = {"file_path": "images/a.png", "transform_matrix": pose(0, (0, 0, 0)), **frame_extra}
    fx, fy, cx, cy = K
    write_json(root / "transforms.json", {"camera_model": camera_model, "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy,
                                          "w": W, "h": H, **coeffs, "frames": [frame]})


RADTAN = {"k1": -0.28, "k2": 0.07, "p1": 0.0012, "p2": -0.0018}
FISHEYE = {"k1": 0.05, "k2": -0.01, "k3": 0.004, "k4": -0.001}


def test_radial_tangential_is_undone_to_the_pinhole_projection(tmp_path):
    img = _render(_opencv_inverse([RADTAN[k] for k in ("k1", "k2", "p1", "p2")]))
    _nerfstudio(tmp_path, "OPENCV", RADTAN, img)
    assert dot_errors(img, K).max() > 1.0, "the test's distortion must be visible to be undone"
    v = load_views(tmp_path)
    errs = dot_errors(v.images[0].numpy(), v.intrinsics[0].tolist())
    print(f"OPENCV: {len(errs)} dots, error mean {errs.mean():.3f} max {errs.max():.3f} px")
    assert len(errs) >= 15 and errs.max() < 0.1, errs
    assert v.images.shape == (1, H, W, 3) and float(v.images.min()) > 0.15, "every pixel has a source: no black border"
    assert v.meta["lens"]["undistorted"] and any("lens distortion undone" in n for n in v.meta["notes"])
    assert not any("distortion ignored" in n for n in v.meta["notes"])

    small = load_views(tmp_path, width=48)  # undistorted at 96 px, then downscaled
    errs = dot_errors(small.images[0].numpy(), small.intrinsics[0].tolist())
    print(f"OPENCV at width 48: error mean {errs.mean():.3f} max {errs.max():.3f} px")
    assert errs.max() < 0.1 and torch.allclose(small.intrinsics[0], v.intrinsics[0] / 2)


def test_undistort_false_keeps_the_distortion_and_says_so(tmp_path):
    img = _render(_opencv_inverse([RADTAN[k] for k in ("k1", "k2", "p1", "p2")]))
    _nerfstudio(tmp_path, "OPENCV", RADTAN, img)
    v = load_views(tmp_path, undistort=False)
    assert v.intrinsics[0].tolist() == pytest.approx(K)
    assert np.abs(v.images[0].numpy() - np.round(img * 255) / 255).max() < 1e-6, "the image as it is on disk"
    assert any("lens distortion ignored (k1, k2, p1, p2)" in n for n in v.meta["notes"])
    assert v.meta["lens"] == {"models": ["nerfstudio OPENCV"], "undistorted": False, "done": "ignored (undistort=False)"}
    errs = dot_errors(v.images[0].numpy(), v.intrinsics[0].tolist())
    print(f"OPENCV ignored: error mean {errs.mean():.3f} max {errs.max():.3f} px")
    assert errs.max() > 1.0  # what ignoring it costs: the rays miss their dots by pixels


def test_fisheye_is_undone_to_the_pinhole_projection(tmp_path):
    img = _render(_opencv_inverse([FISHEYE[k] for k in ("k1", "k2", "k3", "k4")], fisheye=True))
    _nerfstudio(tmp_path, "OPENCV_FISHEYE", FISHEYE, img)
    v = load_views(tmp_path)
    errs = dot_errors(v.images[0].numpy(), v.intrinsics[0].tolist())
    print(f"OPENCV_FISHEYE: {len(errs)} dots, error mean {errs.mean():.3f} max {errs.max():.3f} px")
    assert len(errs) >= 10 and errs.max() < 0.1, errs
    assert float(v.images.min()) > 0.15
    assert v.meta["lens"]["models"] == ["nerfstudio OPENCV_FISHEYE"]


def test_mask_alpha_and_depth_are_undistorted_with_the_image(tmp_path):
    coeffs = [RADTAN[k] for k in ("k1", "k2", "p1", "p2")]
    img = _render(_opencv_inverse(coeffs))
    rgba = np.concatenate([img, np.ones_like(img[:, :, :1])], axis=2)
    rgba[:, :, 3] = 0.6 + 0.4 * (np.arange(W) + 0.5) / W  # an alpha of its own (a ramp), multiplied by the mask
    write_png(tmp_path / "masks/a.png", img)  # the pattern itself as a soft grey mask
    cols, rows = np.meshgrid(np.arange(W), np.arange(H))
    np.save(tmp_path / "depth.npy", (1.0 + cols + 1000.0 * rows).astype(np.float32))  # says which pixel it came from
    _nerfstudio(tmp_path, "OPENCV", RADTAN, rgba, depth_file_path="depth.npy")
    v = load_views(tmp_path)
    assert v.meta["masks"]["count"] == 1 and v.images.shape == (1, H, W, 4)
    fx, fy, cx, cy = v.intrinsics[0].tolist()
    u, w = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pattern = _pattern(np.stack([(u - cx) / fx, (w - cy) / fy], -1))  # the mask as a pinhole sees it
    # where each output pixel came from: the distortion of its ray (cv2.projectPoints)
    rays = np.stack([(u - cx) / fx, (w - cy) / fy, np.ones_like(u)], -1).reshape(-1, 3)
    src, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), opencv_camera_matrix(K), np.array(coeffs))
    src_col = src.reshape(H, W, 2)[..., 0] + 0.5  # our pixel coordinates
    own = 0.6 + 0.4 * src_col / W  # the image's own alpha where the pixel came from
    alpha = v.images[0, ..., 3].numpy()
    err = np.abs(alpha - own * pattern)
    dots = dot_errors((alpha / own)[:, :, None], v.intrinsics[0].tolist())  # the mask's dots, where a pinhole puts them
    print(f"alpha vs the pinhole mask x the image's alpha: max {err.max():.4f}, mean {err.mean():.4f}; "
          f"mask dots off by {dots.max():.3f} px at most")
    assert err.max() < 0.1 and err.mean() < 0.01, "alpha = the image's alpha x the mask, both undistorted (bilinear)"
    assert len(dots) >= 15 and dots.max() < 0.1
    lit = alpha > 0.3
    assert np.abs(v.images[0, ..., 0].numpy() - pattern)[lit].max() < 0.1, "colour undistorted with its alpha"
    depth = v.depth[0].numpy()  # nearest neighbour: the source pixel of each output pixel, exactly
    d_col, d_row = (depth - 1) % 1000, (depth - 1) // 1000
    src_row = src.reshape(H, W, 2)[..., 1] + 0.5
    assert np.abs(d_col + 0.5 - src_col).max() <= 0.5 + 1e-3 and np.abs(d_row + 0.5 - src_row).max() <= 0.5 + 1e-3


def _colmap_render(tmp_path, model: str, params: tuple, w: int = W, h: int = H):
    """A COLMAP model (written by pycolmap) whose two images show the pattern through its lens."""
    import pycolmap

    points, keypoints, _ = colmap_dataset(tmp_path, model=model, params=params, w=w, h=h, distorted_keypoints=True)
    cam = pycolmap.Camera(model=model, width=w, height=h, params=list(params))
    img = _render(lambda uv: cam.cam_from_img(uv))  # COLMAP's own inverse of its model
    for i in range(2):
        write_png(tmp_path / f"images/img{i}.png", img)
    rec = pycolmap.Reconstruction(str(tmp_path / "sparse/0"))
    rec.write_binary(str(tmp_path / "sparse/0"))
    for name in ("cameras", "images", "points3D"):
        (tmp_path / "sparse/0" / f"{name}.txt").unlink()
    return points, keypoints


@pytest.mark.parametrize("model, params", [
    ("SIMPLE_RADIAL", (70.0, 47.3, 36.8, -0.15)),
    ("RADIAL", (70.0, 47.3, 36.8, -0.25, 0.06)),
    ("OPENCV", (70.0, 72.0, 47.3, 36.8, -0.28, 0.07, 0.0012, -0.0018)),
    ("FULL_OPENCV", (70.0, 72.0, 47.3, 36.8, -0.25, 0.05, 0.001, -0.001, 0.01, 0.02, -0.01, 0.005)),
    ("OPENCV_FISHEYE", (70.0, 72.0, 47.3, 36.8, 0.05, -0.01, 0.004, -0.001)),
    ("RADIAL_FISHEYE", (70.0, 47.3, 36.8, 0.05, -0.01)),
])
def test_colmap_lenses_are_undone_with_their_sparse_depth(tmp_path, model, params):
    points, keypoints = _colmap_render(tmp_path, model, params)
    v = load_views(tmp_path)
    errs = dot_errors(v.images[0].numpy(), v.intrinsics[0].tolist())
    print(f"COLMAP {model}: {len(errs)} dots, error mean {errs.mean():.3f} max {errs.max():.3f} px")
    assert len(errs) >= 10 and errs.max() < 0.1, errs
    assert v.meta["lens"] == {"models": [f"COLMAP {model}"], "undistorted": True,
                                    "done": "undistorted at load (OpenCV), pinhole intrinsics replaced"}
    # the sparse depth sits where the pinhole camera projects each 3-D point
    from agent.camera import project_points

    pts = torch.from_numpy(points)
    for i, (_, z) in enumerate(keypoints):
        uv, depth = project_points(v.c2w[i].double().expand(len(pts), 4, 4), v.intrinsics[i].double().expand(len(pts), 4), pts)
        assert torch.allclose(depth, torch.from_numpy(z), rtol=1e-6)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        assert torch.allclose(v.depth[i][row, col].double(), depth, rtol=1e-5)
        assert int((v.depth[i] > 0).sum()) == len(set(zip(col.tolist(), row.tolist())))


def test_a_procedural_lens_is_undone_as_a_datasets_would_be():
    """The in-memory procedural capture with a lens goes through the loaders' undistortion too."""
    from agent.data.loaders import load_views

    raw = load_views("procedural:views=2,width=32,room=1,k1=0.06", undistort=False)
    v = load_views("procedural:views=2,width=32,room=1,k1=0.06")
    assert raw.meta["distortion"]["k1"] == 0.06 and "distortion" not in v.meta
    assert v.meta["lens"]["undistorted"] and any("lens distortion undone" in n for n in v.meta["notes"])
    assert float(v.intrinsics[0, 0]) != float(raw.intrinsics[0, 0]) and v.images.shape == raw.images.shape
