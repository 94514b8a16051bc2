"""Per-robot SfM (agent.data.sfm): poses up to Sim(3), sparse depth, cache, errors."""

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from agent import geometry as G
from agent.data.sfm import CAMERA_FILE, SfmConfig, run_sfm, write_camera_file
from agent.data.views import DataError
from tests.align.scene import TexturedScene, render_views, ring_cameras, save_rgba

DATA = Path(__file__).resolve().parents[2].parent / "shared/data"
LEGO = DATA / "nerf_synthetic/lego"


def _aligned_errors(est_c2w: torch.Tensor, true_c2w: torch.Tensor) -> tuple[np.ndarray, np.ndarray, torch.Tensor]:
    """Sim(3)-align the estimated camera centres to the truth; per-view rotation (deg) and centre errors."""
    t = G.umeyama(est_c2w[:, :3, 3].double(), true_c2w[:, :3, 3].double())
    aligned = G.transform_c2w(t, est_c2w.double())
    rot = np.array([float(G.rotation_angle_deg(aligned[i, :3, :3], true_c2w[i, :3, :3].double()))
                    for i in range(len(est_c2w))])
    centre = (aligned[:, :3, 3] - true_c2w[:, :3, 3].double()).norm(dim=1).numpy()
    return rot, centre, t


def test_sfm_on_rendered_views_recovers_poses_depth_and_caches(tmp_path):
    truth = render_views(TexturedScene(0), ring_cameras(np.arange(0, 120, 10)), 200, 150, 190.0)
    folder = tmp_path / "robot"
    save_rgba(truth, folder)  # RGBA files: SfM must composite them on white itself
    cache = tmp_path / "cache"

    views = run_sfm(folder, cache)
    assert len(views) == 12 and views.meta["unregistered"] == [] and not views.meta["cache_hit"]
    assert views.names == truth.names and views.images.shape == truth.images.shape
    assert abs(float(views.intrinsics[0, 0]) - 190.0) < 10 and torch.allclose(views.intrinsics[0, 2:], torch.tensor([100.0, 75.0]))
    rot, centre, t = _aligned_errors(views.c2w, truth.c2w)
    assert rot.max() < 1.5 and centre.max() < 0.1, (rot, centre)  # ring radius 5

    # Sparse depth prior: z-depth in SfM units, i.e. the true depth divided by the SfM->true scale.
    scale = float(G.sim3_decompose(t)[0])
    has = views.depth > 0
    assert int(has.sum()) > 12 * 50
    true_d = truth.depth[has]
    ok = true_d > 0
    rel = ((views.depth[has][ok] * scale - true_d[ok]).abs() / true_d[ok]).numpy()
    assert np.median(rel) < 0.01 and (rel < 0.05).mean() > 0.9

    # A second call returns from the cache, quickly and identically.
    t0 = time.perf_counter()
    again = run_sfm(folder, cache)
    assert again.meta["cache_hit"] and time.perf_counter() - t0 < 2.0
    assert torch.equal(again.c2w, views.c2w) and torch.equal(again.depth, views.depth)
    # Width: intrinsics and depth follow the output size.
    half = run_sfm(folder, cache, width=100)
    assert half.meta["cache_hit"] and half.images.shape[1:3] == (75, 100)
    assert torch.allclose(half.intrinsics, views.intrinsics * 0.5)
    # A changed image invalidates the cache.
    img = cv2.imread(str(folder / "v003.png"), cv2.IMREAD_UNCHANGED)
    img[:10, :10] = 0
    cv2.imwrite(str(folder / "v003.png"), img)
    assert not run_sfm(folder, cache).meta["cache_hit"]


def test_a_calibrated_camera_keeps_its_focal_length(tmp_path):
    truth = render_views(TexturedScene(0), ring_cameras(np.arange(0, 120, 10)), 200, 150, 190.0)
    robot = tmp_path / "robot"
    save_rgba(truth, robot / "images")  # the split's layout: <robot>/images/*.png, <robot>/camera.json
    write_camera_file(robot, focal_px=380.0, width=400)  # the calibration may be at another resolution
    views = run_sfm(robot, tmp_path / "cache", width=100)
    assert views.meta["focal_calibrated"] and len(views) == 12
    assert torch.allclose(views.intrinsics[:, 0], torch.tensor(95.0))  # 380 px at 400 -> 95 at 100: kept exactly
    rot, centre, _ = _aligned_errors(views.c2w, truth.c2w)
    assert rot.max() < 1.5 and centre.max() < 0.1, (rot, centre)

    # A trainer on such views does not refine the focal length, even with camera refinement on.
    from agent.trainer import CameraRefineConfig, RobotTrainer, TrainConfig

    box = G.box_from_center(torch.zeros(3), 2.0)
    cfg = TrainConfig(cameras=CameraRefineConfig(enabled=True))
    assert not RobotTrainer(views, cfg, box).log_focal.requires_grad
    views.meta["focal_calibrated"] = False
    assert RobotTrainer(views, cfg, box).log_focal.requires_grad

    # Without the file SfM estimates the focal length itself (a new cache key, not the old result).
    (robot / CAMERA_FILE).unlink()
    free = run_sfm(robot, tmp_path / "cache", width=100)
    assert not free.meta["cache_hit"] and not free.meta["focal_calibrated"]


def test_a_robots_sfm_frame_survives_a_change_of_settings(tmp_path):
    """keep_frame (the run's own SfM, as the daemon and the report load it): new settings, e.g. from
    a newer version of this code, reuse the SfM the robot trained in instead of making another
    frame under its checkpoint; new images still recompute."""
    truth = render_views(TexturedScene(0), ring_cameras(np.arange(0, 120, 10)), 200, 150, 190.0)
    folder = tmp_path / "robot"
    save_rgba(truth, folder)
    cache = tmp_path / "cache"
    first = run_sfm(folder, cache)
    other = SfmConfig(max_num_features=3000)
    kept = run_sfm(folder, cache, config=other, keep_frame=True)
    assert kept.meta["cache_hit"] and kept.meta["sfm_settings_changed"]
    assert torch.equal(kept.c2w, first.c2w)
    same = run_sfm(folder, cache, keep_frame=True)
    assert same.meta["cache_hit"] and not same.meta["sfm_settings_changed"]
    assert not run_sfm(folder, cache, config=other).meta["cache_hit"]  # without keep_frame: the new settings
    img = cv2.imread(str(folder / "v003.png"), cv2.IMREAD_UNCHANGED)
    img[:10, :10] = 0
    cv2.imwrite(str(folder / "v003.png"), img)
    assert not run_sfm(folder, cache, config=other, keep_frame=True).meta["cache_hit"]


def test_images_only_folders_load_with_their_run_s_sfm_kept(tmp_path, monkeypatch):
    """load_views(..., sfm_cache_dir=...) is how the daemon and the report load a robot: it keeps the frame."""
    import agent.data.sfm as sfm
    from agent.data.loaders import load_views

    seen = {}

    def fake(image_dir, cache_dir=None, *, width=None, config=SfmConfig(), keep_frame=False):
        seen.update(cache_dir=cache_dir, keep_frame=keep_frame)
        raise DataError("stop here")

    monkeypatch.setattr(sfm, "run_sfm", fake)
    folder = tmp_path / "robot" / "images"
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / "a.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DataError, match="stop here"):
        load_views(tmp_path / "robot", sfm_cache_dir=tmp_path / "cache")
    assert seen == {"cache_dir": tmp_path / "cache", "keep_frame": True}


@pytest.mark.parametrize("text, match", [
    ("not json", "not readable JSON"),
    ("[1, 2]", "expected an object"),
    ('{"focal_px": -3, "width": 400}', "focal_px must be a positive"),
    ('{"focal_px": 500}', "width must be"),
    ('{"focal_px": 500, "width": 400, "fixed": "yes"}', "fixed must be"),
])
def test_a_bad_camera_file_is_a_clear_error(tmp_path, text, match):
    folder = tmp_path / "robot"
    folder.mkdir()
    cv2.imwrite(str(folder / "a.png"), np.zeros((8, 8, 3), np.uint8))
    (folder / CAMERA_FILE).write_text(text)
    with pytest.raises(DataError, match=match):
        run_sfm(folder, tmp_path / "cache")


def test_sfm_errors_are_clear(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match="no images"):
        run_sfm(empty)
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):  # unrelated random images: nothing registers
        cv2.imwrite(str(noise / f"n{i}.png"), rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    with pytest.raises(DataError, match=r"registered \d+ of 4 images"):
        run_sfm(noise, tmp_path / "cache")
    with pytest.raises(DataError, match="does not exist"):
        run_sfm(tmp_path / "missing")


@pytest.mark.data
@pytest.mark.skipif(not LEGO.is_dir(), reason=f"{LEGO} is absent (shared data not mounted)")
def test_sfm_on_a_few_lego_views_agrees_with_the_truth(tmp_path):
    loaders = pytest.importorskip("agent.data.loaders", reason="agent.data.loaders (transforms.json reader) not available")
    truth = loaders.load_views(LEGO)
    centres = truth.c2w[:, :3, 3]
    azimuth = torch.rad2deg(torch.atan2(centres[:, 1], centres[:, 0]))
    idx = [int(i) for i in torch.nonzero((azimuth > -30) & (azimuth < 30)).flatten()][:14]
    folder = tmp_path / "lego"
    folder.mkdir()
    for i in idx:  # the original RGBA files, as a robot with images only would have them
        (folder / f"{truth.names[i]}.png").write_bytes((LEGO / "train" / f"{truth.names[i]}.png").read_bytes())
    views = run_sfm(folder, tmp_path / "cache", config=SfmConfig(max_image_size=400))
    # Coverage is traded for correctness (COLMAP's 30-inlier rule): 10 of these 13 register.
    assert len(views) >= 0.6 * len(idx), views.meta["unregistered"]
    assert len(views) + len(views.meta["unregistered"]) == len(idx)
    true_c2w = truth.c2w[[truth.names.index(n) for n in views.names]]
    rot, centre, _ = _aligned_errors(views.c2w, true_c2w)
    assert rot.max() < 2.0 and np.median(rot) < 1.0 and np.median(centre) < 0.05, (rot, centre)  # radius ~4
