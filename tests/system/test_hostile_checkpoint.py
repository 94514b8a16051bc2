"""`dinerf-agent up` on a run folder whose checkpoint is hostile, damaged or someone else's.

Each is refused before any training: exit code 2, one line ``error: ...`` on stderr, no
traceback, no hang (a FIFO), and the file is still there, byte for byte (the user may want to
look at it). A pickle's payload never runs. The genuine checkpoints that the spoiled ones start
from are made in this process exactly as the daemon makes them (same robot, same model
signature); the out-of-range one carries a valid checksum (rounds and steps out of range:
tests/unit/test_checkpoint.py). Only the temporary file of a killed save goes.
"""

from __future__ import annotations

import os
import pickle
import shutil
import subprocess

import pytest
import torch

from agent.checkpoint import CHECKPOINT, LEGACY_CHECKPOINT, RobotCheckpoint, RunFolder
from tests.system.harness import AGENT, REPO, make_swarm

pytestmark = pytest.mark.slow


class Payload:
    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))  # unpickling creates the marker file


def genuine_checkpoint(swarm, robot_id: int, signature: str | None = None) -> RobotCheckpoint:
    """Robot ``robot_id``'s checkpoint as its daemon would write it after round 1."""
    from agent.daemon import model_spec
    from agent.data.folder import read_scene
    from agent.data.loaders import load_views
    from agent.swarm import build_robot
    from cli.swarm_file import load_swarm_file

    cfg, base = load_swarm_file(swarm.swarm_file)
    box = read_scene(base / cfg.swarm.scene).box_from_shared
    setup = build_robot(robot_id, load_views(swarm.root / f"robot{robot_id}"), box, cfg.training)
    return RobotCheckpoint(1, robot_id, setup.trainer.state_dict(), False, cfg.training,
                           setup.trainer.box_from_shared.cpu(), signature or model_spec(setup).signature())


def _flip_tensor_byte(path):
    data = bytearray(path.read_bytes())
    data[-100] ^= 0x10  # inside the tensor data, which ends the file
    path.write_bytes(bytes(data))


def _genuine(run, swarm, **kw):
    RunFolder(run).save(genuine_checkpoint(swarm, **kw))
    return run / CHECKPOINT


def _out_of_range(run, swarm, spoil):
    """A checkpoint whose checksum is valid but whose values no run can produce, beside the
    temporary file a save killed mid-write left (pid 2**22 + 1 is above Linux's pid_max)."""
    ck = genuine_checkpoint(swarm, robot_id=1)
    spoil(ck)
    RunFolder(run).save(ck)
    (run / f".{CHECKPOINT}.{2**22 + 1}.0badc0de.tmp").write_bytes(b"half a save")


STALE = f".{CHECKPOINT}.{2**22 + 1}.0badc0de.tmp"


CASES = {
    "pickle": (lambda run, swarm: (run / CHECKPOINT).write_bytes(pickle.dumps(Payload(run / "pwned"))), "pickle"),
    "old_pickle": (lambda run, swarm: torch.save(Payload(run / "pwned"), run / LEGACY_CHECKPOINT), "older dinerf"),
    "flipped_byte": (lambda run, swarm: _flip_tensor_byte(_genuine(run, swarm, robot_id=1)), "checksum mismatch"),
    "truncated": (lambda run, swarm: (p := _genuine(run, swarm, robot_id=1)).write_bytes(p.read_bytes()[:-4096]),
                  "truncated: its tensors need"),
    "other_robot": (lambda run, swarm: _genuine(run, swarm, robot_id=2), "robot 2's checkpoint, not robot 1's"),
    "other_model": (lambda run, swarm: _genuine(run, swarm, robot_id=1, signature="another model"),
                    "differs from the configured one"),
    "directory": (lambda run, swarm: (run / CHECKPOINT).mkdir(), "is a directory"),
    "old_directory": (lambda run, swarm: (run / LEGACY_CHECKPOINT).mkdir(), "is a directory"),
    "empty": (lambda run, swarm: (run / CHECKPOINT).write_bytes(b""), "empty"),
    "fifo": (lambda run, swarm: os.mkfifo(run / CHECKPOINT), "is a FIFO"),
    "dev_zero": (lambda run, swarm: (run / CHECKPOINT).symlink_to("/dev/zero"), "outside"),
    "nan_weights": (lambda run, swarm: _out_of_range(
        run, swarm, lambda ck: ck.trainer["field"]["encoding.table"].view(-1).__setitem__(3, float("nan"))),
        "trainer/field/encoding.table holds NaN"),
}


@pytest.fixture(scope="module")
def swarm(tmp_path_factory):
    return make_swarm(tmp_path_factory.mktemp("hostile"), robots=2)


def _snapshot(run):
    return {p.name: (p.read_bytes() if p.is_file() and not p.is_fifo() and not p.is_symlink() else "other")
            for p in run.iterdir()}


@pytest.mark.parametrize("case", sorted(CASES))
def test_up_refuses_a_bad_checkpoint_in_one_line_and_keeps_it(swarm, tmp_path, case):
    spoil, why = CASES[case]
    run = tmp_path / "run"
    run.mkdir()
    spoil(run, swarm)
    before = _snapshot(run)
    res = subprocess.run(AGENT + ["up", "--id", "1", "--data", str(swarm.root / "robot1"), "--run-dir", str(run)],
                         cwd=REPO, capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200"))
    lines = res.stderr.strip().splitlines()  # the log lines (timestamped) before it, then the error
    assert res.returncode == 2, res.stdout[-2000:] + res.stderr[-2000:]
    errors = [line for line in lines if line.startswith("error:")]
    assert errors == lines[-1:] and why in errors[0], res.stderr
    assert "Traceback" not in res.stdout + res.stderr
    assert not (run / "pwned").exists(), "the checkpoint's code ran"
    after = _snapshot(run)
    assert STALE not in after, "the temporary file of a killed save is still there"
    assert {k: v for k, v in after.items() if k in before} == {k: v for k, v in before.items() if k != STALE}, \
        "the refused file was changed"
    shutil.rmtree(run)
