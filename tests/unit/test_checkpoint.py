"""A robot's checkpoint (agent.checkpoint): resuming continues bit for bit; foreign files are refused."""

from __future__ import annotations

import torch

import pytest

from agent.checkpoint import CHECKPOINT, LEGACY_CHECKPOINT, CheckpointError, RobotCheckpoint, RunFolder, load_into
from agent.config_io import from_dict
from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box
from agent.geometry import box_from_center
from agent.swarm import SwarmTrainingConfig, build_robot
from tests.system.harness import TINY_TRAINING
from tests.unit.test_statefile import _same

N, M = 10, 14  # the occupancy grid updates at steps 16 and 24: after the restart


@pytest.fixture(scope="module")
def robot():
    views = load_views("procedural:views=12,width=16")
    center, half, _ = estimate_scene_box(views)
    training = from_dict(SwarmTrainingConfig, {**TINY_TRAINING, "rounds": 2, "steps_per_round": 12})
    return views, box_from_center(center, half), training


def _trainer(robot, robot_id=1):
    views, box, training = robot
    return build_robot(robot_id, views, box, training).trainer


def _neighbour(trainer):
    """A fixed theta_j, so that the consensus terms and the per-edge duals take part."""
    return {2: {k: v + 0.01 for k, v in trainer.theta().items()}}


def _checkpoint(trainer, robot, robot_id=1, signature="sig") -> RobotCheckpoint:
    return RobotCheckpoint(1, robot_id, trainer.state_dict(), False, robot[2], robot[1], signature)


def test_a_resumed_trainer_continues_bit_identically_to_one_that_never_stopped(robot, tmp_path):
    torch.set_num_threads(1)
    straight, first = _trainer(robot), _trainer(robot)
    nb = _neighbour(straight)
    for t in (straight, first):
        t.begin_round(0, nb)
        t.train(N)
        t.end_round(nb)
    folder = RunFolder(tmp_path / "run")
    folder.save(_checkpoint(first, robot))
    del first

    ck = folder.load(robot_id=1)
    assert ck.round == 1 and ck.training == robot[2] and torch.equal(ck.box_from_shared, robot[1])
    resumed = _trainer(robot)
    load_into(resumed, folder.checkpoint, ck.trainer)
    for t in (straight, resumed):
        t.begin_round(1, nb)
        t.train(M)
        t.end_round(nb)
    assert resumed.step == straight.step == N + M
    _same(straight.state_dict(), resumed.state_dict())


def test_another_robots_checkpoint_and_an_old_pickle_are_refused(robot, tmp_path):
    folder = RunFolder(tmp_path / "run")
    folder.save(_checkpoint(_trainer(robot, 2), robot, robot_id=2))
    with pytest.raises(CheckpointError, match="robot 2's checkpoint, not robot 1's"):
        folder.load(robot_id=1)
    (tmp_path / "run" / CHECKPOINT).unlink()
    torch.save({"round": 3}, tmp_path / "run" / LEGACY_CHECKPOINT)
    with pytest.raises(CheckpointError, match="older dinerf"):
        folder.load(robot_id=1)
    assert (tmp_path / "run" / LEGACY_CHECKPOINT).is_file()
    assert RunFolder(tmp_path / "empty").load() is None


def test_a_state_of_another_model_does_not_load_into_the_trainer(robot, tmp_path):
    views, box, training = robot
    other = from_dict(SwarmTrainingConfig, {**TINY_TRAINING, "train": {"field": {"density_hidden": 16}}})
    state = build_robot(1, views, box, other).trainer.state_dict()
    with pytest.raises(CheckpointError, match="does not fit this model") as e:
        load_into(_trainer(robot), tmp_path / CHECKPOINT, state)
    assert "\n" not in str(e.value)


def test_round_snapshots_are_kept_per_round_and_checked_for_their_robot(robot, tmp_path):
    trainer = _trainer(robot)
    folder = RunFolder(tmp_path / "run")
    folder.save_round(1, trainer, robot_id=1)
    folder.save_round(3, trainer, robot_id=1)
    assert folder.snapshot_rounds() == [1, 3]
    snap = folder.load_round(3, robot_id=1)
    _same(trainer.field.state_dict(), snap["field"])
    with pytest.raises(CheckpointError, match="not robot 2's round 3"):
        folder.load_round(3, robot_id=2)
    with pytest.raises(CheckpointError, match="no snapshot of round 2"):
        folder.load_round(2, robot_id=1)


@pytest.mark.parametrize("spoil, why", [
    (lambda ck: setattr(ck, "round", 10**12), "round 1000000000000 is outside 0..2"),
    (lambda ck: setattr(ck, "round", -3), "round -3 is outside"),
    (lambda ck: ck.trainer.__setitem__("step", 10**9), "1000000000 steps after 1 rounds of 12"),
    (lambda ck: ck.trainer.__setitem__("step", -1), "-1 steps"),
    (lambda ck: ck.trainer["field"]["encoding.table"].view(-1).__setitem__(5, float("nan")),
     "trainer/field/encoding.table holds NaN"),
    (lambda ck: ck.trainer["optimizer"]["state"][0]["exp_avg_sq"].view(-1).__setitem__(0, float("inf")),
     "trainer/optimizer/state/0/exp_avg_sq holds NaN or infinite"),
    (lambda ck: ck.box_from_shared.__setitem__((0, 0), float("nan")), "box_from_shared holds NaN"),
])
def test_a_checksum_valid_checkpoint_with_values_out_of_range_is_refused(robot, tmp_path, spoil, why):
    """Whoever can write the run folder can write a valid checksum: every field is checked too."""
    trainer = _trainer(robot)
    trainer.begin_round(0, _neighbour(trainer))
    trainer.train(2)
    ck = _checkpoint(trainer, robot)
    ck.box_from_shared = ck.box_from_shared.clone()
    spoil(ck)
    folder = RunFolder(tmp_path / "run")
    folder.save(ck)
    with pytest.raises(CheckpointError, match=why) as e:
        folder.load(robot_id=1)
    assert "\n" not in str(e.value)


def test_temporaries_of_killed_saves_are_removed_and_nothing_else(tmp_path):
    import os
    import subprocess

    run = tmp_path / "run"
    (run / "rounds").mkdir(parents=True)
    gone = subprocess.Popen(["true"])
    gone.wait()  # a pid that no longer runs
    stale = [run / f".checkpoint.safetensors.{gone.pid}.0badc0de.tmp", run / "rounds" / f".00003.safetensors.{gone.pid}.12345678.tmp"]
    live = run / f".checkpoint.safetensors.{os.getppid()}.abcdef01.tmp"  # its writer still runs
    keep = [live, run / "checkpoint.safetensors", run / "notes.tmp", run / f".x.{gone.pid}.nothex!.tmp"]
    for p in stale + keep:
        p.write_bytes(b"x" * 10)
    (run / f".link.{gone.pid}.aaaaaaaa.tmp").symlink_to(run / "checkpoint.safetensors")
    assert RunFolder(run).remove_stale_temporaries() == (2, 20)
    assert not any(p.exists() for p in stale) and all(p.exists() for p in keep)
    assert (run / f".link.{gone.pid}.aaaaaaaa.tmp").is_symlink()  # only regular files go
