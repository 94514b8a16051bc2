"""ROS 2 bags as a robot's data: tf lookups, camera messages, keyframes, and bags read back.

Every bag here is written by the test with ``rosbags``' writer (tests/data/bags.py), or recorded
from the procedural scene by :mod:`agent.data.ros.record`, as a robot records one.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from agent.camera import OPENCV_FROM_OPENGL
from agent.data.loaders import load_views
from agent.data.ros import KeyframeConfig, RosBagConfig, load_bag
from agent.data.ros.decode import camera_model, decode_compressed, decode_image, grey_sharpness
from agent.data.ros.keyframes import plan_keyframes
from agent.data.ros.record import RecordConfig, bag_storage_file, mount_transform, record_bag
from agent.data.ros.tf import NoTransform, TfTree, matrix_quaternion, quaternion_matrix
from agent.data.views import DataError
from agent.geometry import random_rotation
from tests.data import bags


# --- tf ------------------------------------------------------------------------------------------
def _turn_z(deg: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = bags.pose_x(0.0, deg)
    m[:3, 3] = t
    return m


def test_tf_interpolates_by_slerp_composes_statics_and_never_extrapolates():
    tree = TfTree(max_gap_s=0.5)
    mount = _turn_z(90, (0.0, 0.0, 1.0))
    tree.add("base", "cam", 0, mount[:3, 3], matrix_quaternion(mount), static=True)
    for t, (deg, x) in zip((0, 400_000_000), ((0.0, 0.0), (80.0, 2.0))):
        m = _turn_z(deg, (x, 0.0, 0.0))
        tree.add("/odom", "base", t, m[:3, 3], matrix_quaternion(m), static=False)
    tree.finish()
    got = tree.lookup("odom", "cam", 100_000_000)  # a quarter of the way: 20 deg, x = 0.5
    assert np.allclose(got, _turn_z(20.0, (0.5, 0.0, 0.0)) @ mount, atol=1e-9)
    assert tree.describe("cam") == "odom -> base -> cam (s)" and tree.root("cam") == "odom"
    for stamp, reason in ((-1, "outside_tf"), (400_000_001, "outside_tf")):
        with pytest.raises(NoTransform) as e:
            tree.lookup("odom", "cam", stamp)
        assert e.value.reason == reason
    narrow = TfTree(max_gap_s=0.3)
    for t in (0, 400_000_000):
        narrow.add("odom", "base", t, (0, 0, 0), (0, 0, 0, 1), static=False)
    with pytest.raises(NoTransform) as e:
        narrow.finish().lookup("odom", "base", 200_000_000)
    assert e.value.reason == "tf_gap" and "0.400 s" in str(e.value)
    with pytest.raises(NoTransform) as e:
        tree.lookup("odom", "lidar", 0)
    assert e.value.reason == "no_tf_link"
    with pytest.raises(ValueError, match="two parents"):
        tree.add("map", "base", 0, (0, 0, 0), (0, 0, 0, 1), static=False)


def test_quaternions_round_trip_every_rotation():
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        m = np.eye(4)
        m[:3, :3] = random_rotation(g).double().numpy()
        assert np.allclose(quaternion_matrix(m[:3, 3], matrix_quaternion(m)), m, atol=1e-9)


# --- camera messages -------------------------------------------------------------------------------
def test_every_encoding_decodes_to_straight_rgb_and_others_are_refused_by_name():
    rgb = np.random.default_rng(0).integers(0, 256, (4, 5, 3), dtype=np.uint8)
    alpha = np.full((4, 5, 1), 128, np.uint8)
    want = rgb.astype(np.float32) / 255
    cases = {"rgb8": rgb, "bgr8": rgb[:, :, ::-1], "rgba8": np.concatenate([rgb, alpha], 2),
             "bgra8": np.concatenate([rgb[:, :, ::-1], alpha], 2)}
    for enc, px in cases.items():
        out = decode_image(bags.image(0.0, np.ascontiguousarray(px), enc, step=px.shape[1] * px.shape[2] + 3), "/cam")
        assert np.allclose(out[:, :, :3], want), enc
        assert out.shape[2] == (4 if "a" in enc[3:] else 3) and (out.shape[2] == 3 or np.allclose(out[:, :, 3], 128 / 255))
    grey = rgb[:, :, 0]
    assert np.allclose(decode_image(bags.image(0.0, grey, "mono8"), "/cam"), np.repeat(grey[:, :, None] / 255, 3, 2))
    deep = (np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000)
    for big in (False, True):
        out = decode_image(bags.image(0.0, deep, "mono16", bigendian=big), "/cam")
        assert np.allclose(out[:, :, 1], deep / 65535.0)
    with pytest.raises(DataError, match=r"/cam: image encoding 'bayer_rggb8' is not supported"):
        decode_image(bags.image(0.0, rgb, "bayer_rggb8"), "/cam")
    short = bags.image(0.0, rgb, "rgb8")
    short.step = 3  # fewer bytes a row than its pixels take
    with pytest.raises(DataError, match="expected at least"):
        decode_image(short, "/cam")
    ok, png = cv2.imencode(".png", np.concatenate([rgb[:, :, ::-1], alpha], 2))
    out = decode_compressed(bags.compressed(0.0, png.tobytes(), "png"), "/cam/compressed")
    assert out.shape == (4, 5, 4) and np.allclose(out[:, :, :3], want)
    smooth = np.stack([*np.meshgrid(np.linspace(0, 255, 16), np.linspace(40, 200, 16)), np.full((16, 16), 90.0)], 2)
    ok, jpg = cv2.imencode(".jpg", smooth.astype(np.uint8)[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert np.abs(decode_compressed(bags.compressed(0.0, jpg.tobytes(), "jpeg"), "/c") - smooth / 255).mean() < 0.02
    with pytest.raises(DataError, match="compressedDepth"):
        decode_compressed(bags.compressed(0.0, png.tobytes(), "16UC1; compressedDepth"), "/c")
    with pytest.raises(DataError, match="cannot be decoded"):
        decode_compressed(bags.compressed(0.0, b"not a jpeg", "jpeg"), "/c")


def test_camera_info_gives_the_lens_and_refuses_what_is_no_camera():
    plain = camera_model(bags.camera_info(0.0, 16, 12), "/ci")
    assert plain.lens is None and plain.intrinsics == (20.0, 20.0, 8.0, 6.0)  # ROS pixel centres at the index
    radtan = camera_model(bags.camera_info(0.0, 16, 12, d=(0.1, -0.02, 0.001, 0.0, 0.003)), "/ci").lens
    assert radtan.model == "radtan" and radtan.coeffs == (0.1, -0.02, 0.001, 0.0, 0.003)
    rational = camera_model(bags.camera_info(0.0, 16, 12, model="rational_polynomial", d=(0.1, 0, 0, 0, 0, 0.2, 0, 0)), "/ci")
    assert rational.lens.coeffs == (0.1, 0, 0, 0, 0, 0.2, 0, 0)
    fisheye = camera_model(bags.camera_info(0.0, 16, 12, model="equidistant", d=(0.0, 0.0, 0.0, 0.0)), "/ci").lens
    assert fisheye.model == "fisheye"  # an equidistant lens is no pinhole even with k = 0
    with pytest.raises(DataError, match="no usable intrinsics"):
        camera_model(bags.camera_info(0.0, 16, 12, k=(0.0, 0.0, 0.0, 0.0)), "/ci")
    with pytest.raises(DataError, match="'unified' is not supported"):
        camera_model(bags.camera_info(0.0, 16, 12, model="unified", d=(0.1,)), "/ci")


def test_keyframes_follow_the_motion_and_fit_the_budget_over_the_whole_trajectory():
    c2w = np.stack([bags.pose_x(0.01 * i) for i in range(300)])  # 3 units in 300 frames
    plan = plan_keyframes(c2w, KeyframeConfig(min_translation=0.0999, sharpness_window=3, max_keyframes=0))
    assert len(plan.windows) == 30 and plan.windows[1] == [10, 11, 12]
    budget = plan_keyframes(c2w, KeyframeConfig(min_translation=0.1, max_keyframes=12))
    starts = [w[0] for w in budget.windows]
    assert len(starts) <= 12 and starts[-1] > 250 and budget.min_translation > 0.1  # spread to the end
    turning = np.stack([bags.pose_x(0.0, 2.01 * i) for i in range(40)])  # a robot turning on the spot
    assert len(plan_keyframes(turning, KeyframeConfig(min_rotation_deg=10.0)).windows) == 8
    blurred = cv2.GaussianBlur(np.random.default_rng(0).uniform(0, 1, (40, 40, 3)).astype(np.float32), (9, 9), 3)
    assert grey_sharpness(blurred) < 0.1 * grey_sharpness(np.random.default_rng(0).uniform(0, 1, (40, 40, 3)))


# --- bags read back ----------------------------------------------------------------------------------
@pytest.mark.parametrize("storage,encoding", [("mcap", "rgb8"), ("sqlite3", "png")])
def test_a_recorded_bag_gives_back_the_true_poses_in_the_odometry_frame(tmp_path, storage, encoding):
    views = load_views("procedural:views=10,width=32")  # RGBA: a png keeps the alpha (a mask), rgb8 drops it
    offset = np.eye(4)
    offset[:3, :3] = random_rotation(torch.Generator().manual_seed(1)).double().numpy()
    offset[:3, 3] = (1.0, -2.0, 0.5)
    rec = RecordConfig(storage=storage, encoding=encoding, k1=0.05, tf_rate_factor=15)
    info = record_bag(views, tmp_path / "bag", offset, rec)
    assert info["images"] == 10 and info["tf"] >= 140  # 9 image periods at 15 transforms each, and the ends
    source = bag_storage_file(tmp_path / "bag") if storage == "mcap" else tmp_path / "bag"  # a lone file, or the folder
    got = load_bag(source, cfg=RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1)))
    assert got.meta["bag"]["keyframes"] == 10 and got.meta["bag"]["tf_chain"] == "odom -> base_link -> camera_optical (s)"
    truth = torch.from_numpy(offset) @ views.c2w.double()  # the camera in odom, OpenGL
    assert torch.allclose(got.c2w.double(), truth, atol=2e-5)
    assert got.has_alpha == (encoding == "png") and got.meta["lens"]["models"] == ["ROS plumb_bob"]
    assert (got.intrinsics[:, 0] > views.intrinsics[:, 0]).all()  # undistorted: a narrower pinhole
    assert np.allclose(mount_transform(15.0)[:3, :3] @ OPENCV_FROM_OPENGL[:3, :3] @ OPENCV_FROM_OPENGL[:3, :3],
                       mount_transform(15.0)[:3, :3])


def test_the_sharpest_frame_of_each_window_is_kept_and_images_without_a_pose_are_counted(tmp_path):
    sharp = np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    blurred = cv2.GaussianBlur(sharp, (9, 9), 4)
    msgs = [("/tf_static", "tf2_msgs/msg/TFMessage", bags.T0, bags.tf_message(
        bags.transform(bags.T0, "base_link", "cam", np.eye(4))))]
    for k in range(120):  # 100 Hz; the robot moves one unit every 0.3 s, in a step
        t = bags.T0 + 0.01 * k
        msgs.append(("/tf", "tf2_msgs/msg/TFMessage", t, bags.tf_message(
            bags.transform(t, "odom", "base_link", bags.pose_x(float(k // 30))))))
    for i in range(12):  # 4 stops of 3 frames: blurred, sharp, blurred; then 2 frames after the tf ends
        t = bags.T0 + 0.1 * i + 0.005
        px = sharp if i % 3 == 1 else blurred
        msgs.append(("/cam/image_raw", "sensor_msgs/msg/Image", t, bags.image(t, px, "rgb8", "cam")))
    for t in (bags.T0 + 1.5, bags.T0 + 1.6):
        msgs.append(("/cam/image_raw", "sensor_msgs/msg/Image", t, bags.image(t, sharp, "rgb8", "cam")))
    msgs.append(("/cam/camera_info", "sensor_msgs/msg/CameraInfo", bags.T0, bags.camera_info(bags.T0, 32, 24, frame="cam")))
    views = load_bag(bags.write_bag(tmp_path / "stops", msgs), cfg=RosBagConfig(keyframes=KeyframeConfig(sharpness_window=3)))
    assert views.names == ["frame_000001", "frame_000004", "frame_000007", "frame_000010"]
    assert views.meta["bag"]["skipped"] == {"outside_tf": 2} and views.meta["bag"]["posed"] == 12


def test_a_run_folder_keeps_the_keyframes_of_its_first_read(tmp_path):
    bag = bags.camera_bag(tmp_path / "bag", n=6)
    cache = tmp_path / "run" / "keyframes"
    first = load_bag(bag, cfg=RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1)), cache_dir=cache)
    assert (cache / "transforms.json").is_file() and len(first) == 6
    fewer = RosBagConfig(keyframes=KeyframeConfig(min_translation=0.99, sharpness_window=1))  # every 2nd image
    again = load_bag(bag, cfg=fewer, cache_dir=cache)
    assert again.names == first.names and again.meta["bag_settings_changed"]  # the run's views stay its views
    assert len(load_bag(bag, cfg=fewer)) == 3  # read afresh, the new settings apply
