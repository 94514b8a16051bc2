"""The views a robot has now (agent.data.stream): keyframes from a bag as they arrive, on disk,
a bounded few in memory, sampled with a bias to the newest, held out by the loader's rule."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from agent.data.ros import RosBagConfig, extract_keyframes
from agent.data.ros.config import KeyframeConfig
from agent.data.ros.intake import FrameIntake, bag_image_topic, replay_bag
from agent.data.ros.keyframes import OnlineKeyframer, plan_keyframes
from agent.data.stream import StreamConfig, ViewStream
from agent.geometry import box_from_center
from agent.swarm import SwarmTrainingConfig, build_robot, own_holdout_split
from agent.nerf.encoding import HashGridConfig
from agent.nerf.field import FieldConfig
from agent.nerf.occupancy import OccupancyConfig
from agent.trainer import TrainConfig
from tests.data.bags import camera_bag

SMALL = TrainConfig(rays_per_step=64, field=FieldConfig(grid=HashGridConfig(log2_hashmap_size=12, num_levels=8)),
                    occupancy=OccupancyConfig(resolution=32))


def _intake(bag, cfg=None, **kw) -> FrameIntake:
    cfg = cfg or RosBagConfig()
    image, info = bag_image_topic(bag, cfg)
    return FrameIntake(cfg, image, info, **kw)


def _fed(bag, cfg=None) -> FrameIntake:
    intake = _intake(bag, cfg)
    replay_bag(bag, intake, 0.0, threading.Event())
    return intake


def test_online_rule_triggers_where_the_offline_plan_does():
    rng = np.random.default_rng(0)
    c2w = np.tile(np.eye(4), (60, 1, 1))
    c2w[:, 0, 3] = np.cumsum(rng.uniform(0, 0.2, 60))  # irregular steps along x
    cfg = KeyframeConfig(min_translation=0.5, min_rotation_deg=5, sharpness_window=1, max_keyframes=0)
    plan = plan_keyframes(c2w, cfg)
    online = OnlineKeyframer(cfg)
    kept = [i for i in range(60) if online.offer(c2w[i], i, lambda _: 1.0) is not None]
    assert kept == [w[0] for w in plan.windows] and len(kept) > 5
    # the sharpest of each window, and a budget: the rest is dropped and counted
    online = OnlineKeyframer(KeyframeConfig(min_translation=0.5, sharpness_window=3, max_keyframes=4))
    kept = [k for i in range(60) if (k := online.offer(c2w[i], i, lambda f: -abs(f - 41))) is not None]
    assert len(kept) == 4 and online.dropped > 0


def test_intake_poses_keyframes_as_the_bag_loader_does(tmp_path):
    bag = camera_bag(tmp_path / "bag", n=10, moves=0.5)
    cfg = RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1))
    intake = _fed(bag, cfg)
    online = intake.take() + intake.finish()
    extract_keyframes(bag, tmp_path / "kf", cfg)
    import json

    offline = {f["file_path"].split("/")[-1][:-4]: np.array(f["transform_matrix"])
               for f in json.loads((tmp_path / "kf" / "transforms.json").read_text())["frames"]}
    assert [k.name for k in online] == sorted(offline)
    for k in online:
        np.testing.assert_allclose(k.c2w, offline[k.name], atol=1e-6)
        assert k.image.shape == (12, 16, 3)


def test_an_image_ahead_of_tf_waits_then_is_posed(tmp_path):
    bag = camera_bag(tmp_path / "bag", n=4, moves=1.0)
    intake = _intake(bag, RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1)), tf_wait_s=30)
    from agent.data.ros.bag import _Bag

    b = _Bag(bag)
    msgs = list(b.messages(b.connections))
    b.close()
    for conn, _, msg in [m for m in msgs if m[0].topic != "/tf"]:  # images before any /tf
        intake.feed(conn.topic, conn.msgtype, msg)
    assert intake.take() == [] and len(intake._pending) == 4
    for conn, _, msg in [m for m in msgs if m[0].topic == "/tf"]:
        intake.feed(conn.topic, conn.msgtype, msg)
    assert len(intake.take()) == 4 and not intake.skipped


def _stream(tmp_path, n=30, every=5, capacity=300, **cfg) -> ViewStream:
    bag = camera_bag(tmp_path / "bag", n=n, moves=0.5)
    intake = _fed(bag, RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1, max_keyframes=0)))
    stream = ViewStream(StreamConfig(**cfg), intake, tmp_path / "keyframes", None, every, capacity)
    stream.ended.set()
    return stream


def test_held_out_as_the_loader_splits_and_capacity_drops(tmp_path):
    stream = _stream(tmp_path, n=30, every=5, capacity=20)
    stream.admit()
    names = [f["file_path"] for f in stream.store.frames]
    assert len(names) == 30
    index = list(range(30))
    keep = [i for i in index if i % 5 != 4]
    assert [f["file_path"] for f in stream._rows] == [names[i] for i in keep][:20]
    assert [f["file_path"] for f in stream._held] == [names[i] for i in index if i % 5 == 4]
    s = stream.round_stats()
    assert (s.admitted, s.held_out, s.keyframes, s.dropped) == (24, 6, 20, 4)
    assert s.coverage is not None and s.coverage[0] > 0
    assert stream.round_stats().admitted == 0  # per round
    # a restart reads the same folder back and does not add the same frames twice
    again = ViewStream(StreamConfig(), _fed(tmp_path / "bag", RosBagConfig(keyframes=KeyframeConfig(
        sharpness_window=1, max_keyframes=0))), tmp_path / "keyframes", None, 5, 20)
    again.ended.set()
    again.admit()
    assert len(again.store.frames) == 30 and len(again._rows) == 20
    # render, eval and export read the run's streamed keyframes, never the bag again over them
    from agent.data.ros import load_bag

    views = load_bag(tmp_path / "bag", cache_dir=tmp_path / "keyframes")
    assert views.names == [n.split("/")[-1][:-4] for n in names]
    train, held = own_holdout_split(views, 5)
    assert held.names == [f["file_path"].split("/")[-1][:-4] for f in stream._held]


def _trained(tmp_path, **cfg):
    stream = _stream(tmp_path, n=40, every=0, working_set=8, recent_keyframes=2, refresh_every=1, **cfg)
    stream.intake_keyframes = stream._arrived()
    stream._admit(stream.intake_keyframes[:4])
    views = stream.initial_views()
    training = SwarmTrainingConfig(rounds=1, steps_per_round=4, own_holdout_every=0, train=SMALL)
    setup = build_robot(0, views, box_from_center(torch.tensor([10.0, 0, 0]), torch.tensor(15.0)), training,
                        stream=stream)
    return stream, setup


def test_memory_is_bounded_and_every_keyframe_comes_back(tmp_path):
    stream, setup = _trained(tmp_path)
    buffer = stream._buffer
    stream._admit(stream.intake_keyframes[4:])
    assert len(stream._rows) == 40 and stream._buffer is buffer and buffer.shape[0] == 8
    seen = set()
    gen = torch.Generator().manual_seed(0)
    for _ in range(300):
        rows = stream.sample(64, gen, torch.device("cpu"))[0]
        seen |= set(rows.tolist())
        assert len(set(int(r) for r in stream._slot_row)) <= 8
    assert seen == set(range(40))  # the old ones come back in turn
    assert int(stream._slot_row.max()) == 39 and 38 in stream._slot_row.tolist()  # the newest stay in
    # the keyframe summary (served again as they grow) reads a bounded few, spread from first to last
    spread = stream.spread_views(6, width=None)
    xs = sorted(float(c[0, 3]) for c in spread.c2w)
    all_xs = sorted(float(f["transform_matrix"][0][3]) for f in stream._rows)
    assert len(spread.names) == 6 and spread.images.shape[2] == stream.store.camera["w"]
    assert [xs[0], xs[-1]] == pytest.approx([all_xs[0], all_xs[-1]], abs=1e-5) and all_xs[-1] - all_xs[0] > 1
    assert len(stream.spread_views(100).names) == 40


@pytest.mark.parametrize("sampling", ["recency", "uniform"])
def test_recency_favours_the_newest(tmp_path, sampling):
    stream, setup = _trained(tmp_path, sampling=sampling, recent_fraction=0.5)
    stream._admit(stream.intake_keyframes[4:])
    gen = torch.Generator().manual_seed(0)
    rows = torch.cat([stream.sample(256, gen, torch.device("cpu"))[0] for _ in range(50)])
    newest = float((rows >= 38).float().mean())
    expected = 0.5 + 0.5 * 2 / 8 if sampling == "recency" else 2 / 8
    assert newest == pytest.approx(expected, abs=0.03)


def test_training_on_a_growing_set_keeps_its_shapes_and_opens_the_grid(tmp_path):
    stream, setup = _trained(tmp_path)
    trainer = setup.trainer
    assert trainer.view_phi.shape[0] == 300 and trainer.appearance.params.shape[0] == 300
    trainer.train(4)
    state = trainer.state_dict()
    trainer.grid.occupied[:] = False  # as if pruned
    stream._admit(stream.intake_keyframes[4:9])  # further along, looking where the first ones looked
    assert int(trainer.grid.occupied.sum()) == 0  # what a keyframe saw is the field's to prune, not reopened
    import dataclasses

    kf = stream.intake_keyframes[9]
    back = kf.c2w.copy()
    back[:3, :3] = back[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned round: space no keyframe has seen
    stream._admit([dataclasses.replace(kf, c2w=back)])
    assert int(trainer.grid.occupied.sum()) > 0
    np.testing.assert_allclose(trainer.c2w_local[9].numpy(), back, atol=1e-6)
    trainer.train(4)
    trainer.load_state_dict(state)  # checkpoints from before the growth still load
    assert trainer.step == 4
    # render, eval, export: the run's keyframes read back as a folder, the checkpoint's rows kept
    from agent.checkpoint import view_rows

    final = trainer.state_dict()
    again = build_robot(0, stream.initial_views(), trainer.box_from_shared, SwarmTrainingConfig(
        rounds=1, steps_per_round=4, own_holdout_every=0, train=SMALL), view_rows=view_rows(final)).trainer
    again.load_state_dict(final)
    assert again.view_phi.shape[0] == 300 and len(again.views) == 10


def test_the_round_line_and_status_say_what_the_stream_did():
    from agent.telemetry import RoundRecord
    from cli.cmd_status import _views
    from tests.protocol.helpers import status_message

    record = RoundRecord(robot=1, round=3, loss=0.01, pose_rotation_deg=0.0, pose_translation=[0, 0, 0], pose_scale=1.0,
                         keyframes=42, keyframes_admitted=3, keyframes_held_out=1, keyframes_dropped=0,
                         keyframe_age_s=0.4, coverage=[2.0, 1.0, 0.25])
    assert "keyframes 42 (+3, held out +1, dropped +0) newest 0.4 s ago, area 2.00 x 1.00 x 0.25" in record.log_line(10)
    assert RoundRecord.from_dict(__import__("json").loads(record.to_json())) == record
    assert "keyframes" not in RoundRecord(robot=1, round=3, loss=0.01, pose_rotation_deg=0.0, pose_translation=[0, 0, 0],
                                          pose_scale=1.0).log_line(10)
    views = {"keyframes": 42, "held_out": 5, "dropped": 1, "newest_age_s": 0.4, "coverage": [2.0, 1.0, 0.25]}
    assert _views(status_message(views=views)) == "42 (+5 held, 1 dropped), newest 0.4 s, area 2.0 x 1.0 x 0.2"


def test_images_without_camera_info_are_dropped_not_hoarded(tmp_path):
    bag = camera_bag(tmp_path / "bag", n=6)
    intake = _intake(bag, tf_wait_s=0.0)
    from agent.data.ros.bag import _Bag

    b = _Bag(bag)
    for conn, _, msg in b.messages([c for c in b.connections if c.topic != "/camera/camera_info"]):
        intake.feed(conn.topic, conn.msgtype, msg)
    b.close()
    assert intake.take() == [] and intake._pending == [] and intake.skipped["no_camera_info"] == 6
