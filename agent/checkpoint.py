"""A robot's run folder: what the daemon keeps on disk, under which names, and how it comes back.

::

    <run dir>/checkpoint.safetensors   the robot's whole state after its last completed round
    <run dir>/rounds/<k>.safetensors   field + grid + pose after round k (``daemon.keep_rounds``), for reports
    <run dir>/telemetry.jsonl          one agent.telemetry.RoundRecord per completed round
    <run dir>/events.jsonl             joins, alignment, failovers, silent neighbours ...
    <run dir>/done.json                written once every round is done
    <run dir>/data.json                the robot's data folder (and swarm file), so that outputs find its views
    <run dir>/config.toml              the configuration it runs with, every default written out
    <run dir>/sfm/                     an images-only robot's own SfM, computed once, reused on restart
    <run dir>/keyframes/               a robot with a ROS 2 bag: its keyframes, read once (agent.data.ros)

Checkpoints and snapshots are state files (``agent.statefile``: safetensors + JSON, checksummed,
written atomically); ``done.json`` is written atomically too. A file that cannot be used is
refused with a :class:`CheckpointError` and left in place. A ``checkpoint.pt`` of an older
dinerf is a pickle: it is refused, never loaded. A checksum proves no more than that the file is
whole, so every field of a checkpoint is range-checked too (its round, its steps, finite
weights). A save killed mid-write leaves ``.<name>.<pid>.<hex>.tmp`` behind;
:meth:`RunFolder.remove_stale_temporaries` removes those of processes that are gone.
"""

from __future__ import annotations

import json
import os
import re
import stat
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agent.config_io import ConfigError, from_dict, to_dict
from agent.data.views import Views
from agent.files import atomic_write_text
from agent.statefile import CheckpointError, read_state, write_state
from agent.swarm import RobotSetup, SwarmTrainingConfig, build_robot
from agent.trainer import RobotTrainer, TrainConfig

__all__ = ["RunFolder", "RobotCheckpoint", "CheckpointError", "CHECKPOINT", "SFM_CACHE", "KEYFRAME_CACHE", "load_for_eval",
           "load_robot",
           "save_baseline", "load_baseline"]

CHECKPOINT = "checkpoint.safetensors"
LEGACY_CHECKPOINT = "checkpoint.pt"  # torch.save of dinerf before state files: refused
SNAPSHOT_SUFFIX = ".safetensors"
SFM_CACHE = "sfm"
KEYFRAME_CACHE = "keyframes"
ROUNDS = "rounds"
TELEMETRY = "telemetry.jsonl"
EVENTS = "events.jsonl"
DONE = "done.json"
DATA_RECORD = "data.json"  # absent in run folders of dinerf before it: commands then ask for --data
ROBOT_KIND, ROUND_KIND, BASELINE_KIND = "robot-checkpoint", "round-snapshot", "baseline"


@dataclass
class RobotCheckpoint:
    """Everything a robot needs to resume, and to be rebuilt for evaluation."""

    round: int
    robot_id: int
    trainer: dict  # RobotTrainer.state_dict()
    elected: bool  # it was the reference (pose frozen)
    training: SwarmTrainingConfig  # load_for_eval rebuilds the robot from it
    box_from_shared: Tensor  # [4, 4]
    signature: str  # the model spec's: a checkpoint of another model is refused


def _field(path: Path, state: Any, key: str, kind: type | tuple[type, ...]) -> Any:
    """``state[key]``, which must be a ``kind``: a well-formed file of the wrong shape is refused too."""
    if not isinstance(state, dict) or key not in state:
        raise CheckpointError(path, f"malformed state: no {key!r}")
    value = state[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise CheckpointError(path, f"malformed state: {key!r} is a {type(value).__name__}")
    return value


def _non_finite(state: Any, where: str = "") -> str | None:
    """The path of the first floating tensor in ``state`` holding a NaN or an infinity, if any."""
    if isinstance(state, Tensor):
        return where if state.is_floating_point() and not bool(torch.isfinite(state).all()) else None
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, (list, tuple)) else ()
    for key, value in items:
        if (found := _non_finite(value, f"{where}/{key}" if where else str(key))) is not None:
            return found
    return None


def _check_ranges(path: Path, ck: RobotCheckpoint) -> None:
    """A checkpoint that decodes may still say what no run can produce: refused in one line."""
    rounds, per_round = ck.training.rounds, ck.training.steps_per_round
    if not 0 <= ck.round <= rounds:
        raise CheckpointError(path, f"malformed state: round {ck.round} is outside 0..{rounds} (its training.rounds)")
    step = _field(path, ck.trainer, "step", int)
    if not 0 <= step <= ck.round * per_round:
        raise CheckpointError(path, f"malformed state: {step} steps after {ck.round} rounds of {per_round}")
    if (where := _non_finite({"box_from_shared": ck.box_from_shared, "trainer": ck.trainer})) is not None:
        raise CheckpointError(path, f"malformed state: {where} holds NaN or infinite values")


_TEMPORARY = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{8}\.tmp$")  # agent.files.atomic_write_bytes' names


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        return True
    return pid != os.getpid()  # ours: a temporary of this process is never stale at its start


class RunFolder:
    """The files of one robot's run (see the module docstring)."""

    def __init__(self, path: str | Path, create: bool = True) -> None:
        self.path = Path(path)
        if create:
            self.path.mkdir(parents=True, exist_ok=True)

    checkpoint = property(lambda self: self.path / CHECKPOINT)
    telemetry = property(lambda self: self.path / TELEMETRY)
    events = property(lambda self: self.path / EVENTS)
    done = property(lambda self: self.path / DONE)
    data_record = property(lambda self: self.path / DATA_RECORD)
    sfm_cache = property(lambda self: self.path / SFM_CACHE)
    keyframe_cache = property(lambda self: self.path / KEYFRAME_CACHE)

    def round_path(self, round_index: int) -> Path:
        return self.path / ROUNDS / f"{round_index:05d}{SNAPSHOT_SUFFIX}"

    def snapshot_rounds(self) -> list[int]:
        """The rounds kept under ``rounds/`` (``daemon.keep_rounds``), in order."""
        found = (self.path / ROUNDS).glob(f"*{SNAPSHOT_SUFFIX}")
        return sorted(int(p.name[:-len(SNAPSHOT_SUFFIX)]) for p in found if p.name[:-len(SNAPSHOT_SUFFIX)].isdigit())

    def load_views(self, data_dir: str | Path, width: int | None, sfm=None, ros=None) -> Views:
        """The robot's views as its daemon trains on them: at ``width``; images only: through this
        run's SfM; a bag: this run's keyframes (``sfm``, ``ros``: their settings, for a first read)."""
        from agent.data.loaders import load_views

        return load_views(data_dir, width=width, sfm_cache_dir=self.sfm_cache, sfm=sfm, ros=ros,
                          keyframe_cache_dir=self.keyframe_cache)

    def save(self, ck: RobotCheckpoint) -> None:
        write_state(self.checkpoint, ROBOT_KIND, {
            "round": ck.round, "robot_id": ck.robot_id, "elected": ck.elected, "signature": ck.signature,
            "training": to_dict(ck.training), "box_from_shared": ck.box_from_shared, "trainer": ck.trainer})

    def save_round(self, round_index: int, trainer: RobotTrainer, robot_id: int) -> None:
        (self.path / ROUNDS).mkdir(exist_ok=True)
        write_state(self.round_path(round_index), ROUND_KIND, {
            "round": round_index, "robot_id": robot_id, "field": trainer.field.state_dict(),
            "grid": trainer.grid.state_dict(), "pose": trainer.pose.state_dict()})

    def load(self, robot_id: int | None = None) -> RobotCheckpoint | None:
        """The checkpoint (robot ``robot_id``'s, if given), or None if there is none.

        Raises :class:`CheckpointError` for one that cannot be used, and for an old pickled one."""
        path = self.checkpoint
        if not path.exists() and not path.is_symlink():
            legacy = self.path / LEGACY_CHECKPOINT
            if legacy.is_dir():
                raise CheckpointError(legacy, "is a directory, not a checkpoint")
            if legacy.exists():
                raise CheckpointError(legacy, "a checkpoint of an older dinerf: a pickle (torch.save), "
                                      "which is never loaded (it could run code)")
            return None
        state = read_state(path, ROBOT_KIND, within=self.path)
        ck = RobotCheckpoint(
            round=_field(path, state, "round", int), robot_id=_field(path, state, "robot_id", int),
            trainer=_field(path, state, "trainer", dict), elected=_field(path, state, "elected", bool),
            training=self._training(path, _field(path, state, "training", dict)),
            box_from_shared=_field(path, state, "box_from_shared", Tensor),
            signature=_field(path, state, "signature", str))
        if robot_id is not None and ck.robot_id != robot_id:
            raise CheckpointError(path, f"robot {ck.robot_id}'s checkpoint, not robot {robot_id}'s")
        if ck.box_from_shared.shape != (4, 4):
            raise CheckpointError(path, f"malformed state: a field box of shape {list(ck.box_from_shared.shape)}")
        _check_ranges(path, ck)
        return ck

    def remove_stale_temporaries(self) -> tuple[int, int]:
        """Remove the temporary files of saves whose process is gone (killed mid-write): regular
        files named as ``agent.files`` names them, here and in ``rounds/``. (count, bytes)."""
        count = size = 0
        for folder in (self.path, self.path / ROUNDS):
            try:
                names = os.listdir(folder)
            except OSError:
                continue
            for name in names:
                match = _TEMPORARY.match(name)
                if match is None or _process_alive(int(match[1])):
                    continue
                try:
                    info = os.lstat(folder / name)
                    if stat.S_ISREG(info.st_mode):
                        os.unlink(folder / name)
                        count, size = count + 1, size + info.st_size
                except OSError:
                    continue
        return count, size

    @staticmethod
    def _training(path: Path, data: dict) -> SwarmTrainingConfig:
        try:
            return from_dict(SwarmTrainingConfig, data, "training")
        except ConfigError as e:
            raise CheckpointError(path, f"its training settings do not load: {e}") from None

    def load_round(self, round_index: int, robot_id: int) -> dict[str, dict]:
        """The field, grid and pose state of snapshot ``rounds/<round_index>``."""
        path = self.round_path(round_index)
        if not path.exists():
            raise CheckpointError(path, f"no snapshot of round {round_index} (kept: {self.snapshot_rounds()})")
        snap = read_state(path, ROUND_KIND, within=self.path)
        if (_field(path, snap, "round", int), _field(path, snap, "robot_id", int)) != (round_index, robot_id):
            raise CheckpointError(path, f"robot {snap['robot_id']}'s round {snap['round']}, "
                                  f"not robot {robot_id}'s round {round_index}")
        return {k: _field(path, snap, k, dict) for k in ("field", "grid", "pose")}

    def write_data_record(self, data_dir: str | Path, swarm_file: str | Path | None = None) -> None:
        """Say where this robot's views come from (absolute paths): render, eval and export read it."""
        doc = {"data": str(Path(data_dir).resolve()),
               "swarm": None if swarm_file is None else str(Path(swarm_file).resolve())}
        atomic_write_text(self.data_record, json.dumps(doc, indent=2) + "\n")

    def write_config(self, toml: str) -> None:
        """``config.toml``: the robot's whole configuration, as ``config show`` prints it."""
        atomic_write_text(self.path / "config.toml", toml)

    def recorded_data_dir(self) -> Path | None:
        """The data folder :meth:`write_data_record` wrote, or None when the run folder has no record."""
        from agent.data.views import DataError
        from agent.files import read_json

        if not self.data_record.is_file():
            return None
        doc = read_json(self.data_record, DataError)
        if not isinstance(doc, dict) or not isinstance(doc.get("data"), str):
            raise CheckpointError(self.data_record, "malformed: expected {\"data\": <folder>}")
        return Path(doc["data"])

    def write_done(self, robot_id: int, rounds: int, rejected: dict[str, int], **extra: Any) -> None:
        """``rounds`` reached; ``extra``: e.g. the steps trained and the joins and skips that
        moved the round otherwise (each taken from a quorum of neighbours)."""
        done = {"robot": robot_id, "rounds": rounds, "time": time.time(), "rejected": rejected, **extra}
        atomic_write_text(self.done, json.dumps(done, indent=2) + "\n")


def load_into(trainer: RobotTrainer, path: Path, state: dict) -> None:
    """``trainer.load_state_dict(state)``; a state that does not fit the trainer is a CheckpointError."""
    try:
        trainer.load_state_dict(state)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as e:
        raise CheckpointError(path, f"does not fit this model ({type(e).__name__}: {e})") from None


def view_rows(state: dict) -> int | None:
    """The rows of a checkpoint's per-view state: more than its views when it trained on a stream
    (capacity allocated up front, agent.data.stream)."""
    phi = (state.get("cameras") or {}).get("phi") if isinstance(state, dict) else None
    return int(phi.shape[0]) if isinstance(phi, Tensor) and phi.ndim == 2 else None


def load_for_eval(run_dir: str | Path, data_dir: str | Path, round: int | None = None,
                  device: str | None = None) -> RobotTrainer:
    """Rebuild a robot's trainer from its run folder (final checkpoint or ``rounds/<k>``).

    device: where to rebuild it (default: the device it trained on), e.g. to render a GPU run on a CPU."""
    return load_robot(run_dir, data_dir, round, device).trainer


def load_robot(run_dir: str | Path, data_dir: str | Path, round: int | None = None,
               device: str | None = None, views: Views | None = None) -> RobotSetup:
    """As :func:`load_for_eval`, with the robot's own held-out views beside its trainer.

    views: the robot's views as :meth:`RunFolder.load_views` gives them, when the caller has them
    already (a report scoring round after round reads them once)."""
    import dataclasses

    from agent.config_io import InvalidValue

    folder = RunFolder(run_dir, create=False)
    ck = folder.load()
    if ck is None:
        raise FileNotFoundError(f"{folder.checkpoint}: no checkpoint")
    training = ck.training
    if device is not None:
        try:
            training = dataclasses.replace(training, train=dataclasses.replace(training.train, device=device))
        except InvalidValue as e:
            raise ConfigError(f"--device: {e}") from None
    views = views if views is not None else folder.load_views(data_dir, training.image_width)
    setup = build_robot(ck.robot_id, views, ck.box_from_shared, training, view_rows=view_rows(ck.trainer))
    trainer = setup.trainer
    load_into(trainer, folder.checkpoint, ck.trainer)
    if round is not None:
        snap = folder.load_round(round, ck.robot_id)
        try:
            trainer.field.load_state_dict(snap["field"])
            trainer.grid.load_state_dict(snap["grid"])
            trainer.pose.load_state_dict(snap["pose"])
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointError(folder.round_path(round), f"does not fit this model ({e})") from None
    return setup


def save_baseline(path: str | Path, trainer: RobotTrainer, cfg: TrainConfig) -> None:
    """The centralised baseline's model (``dinerf-agent baseline``): trainer state + its TrainConfig."""
    write_state(path, BASELINE_KIND, {"trainer": trainer.state_dict(), "config": to_dict(cfg)})


def load_baseline(path: str | Path) -> tuple[dict, TrainConfig]:
    """(trainer state, TrainConfig) of a file :func:`save_baseline` wrote."""
    path = Path(path)
    state = read_state(path, BASELINE_KIND)
    try:
        cfg = from_dict(TrainConfig, _field(path, state, "config", dict), "train")
    except ConfigError as e:
        raise CheckpointError(path, f"its settings do not load: {e}") from None
    return _field(path, state, "trainer", dict), cfg
