"""What the viewer shows, found on disk: the robots of a run folder and their newest models.

A run folder is one of
- a scenario run ``<out>/`` (robot i's run in ``robots/<i>/``, the split in ``data/``);
- the run folders of robots started by hand, ``<dir>/robot<i>/`` (``up``'s default ``runs/<swarm>/``);
- one robot's ``--run-dir`` itself.
A run folder does not say where its robot's images are (only a scenario keeps them beside it), so
the last two need ``--data``: the split folder (holding ``robot<i>/``) or the robot's own folder.
The images are needed: a robot's model is rebuilt from its checkpoint around its own views.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from agent.checkpoint import EVENTS, TELEMETRY, RunFolder, load_into
from agent.data.split import robot_folder
from agent.data.views import DataError, Views
from agent.statefile import CheckpointError
from agent.swarm import build_robot
from agent.telemetry import RoundRecord, read_events, read_telemetry
from agent.trainer import RobotTrainer

__all__ = ["RobotSource", "find_robots", "RobotModel", "RobotStatus"]

_RUN_FILES = ("checkpoint.safetensors", TELEMETRY, EVENTS)


@dataclass(frozen=True)
class RobotSource:
    """One robot of the run: its run folder and the folder of its images."""

    robot_id: int
    run_dir: Path
    data_dir: Path

    @property
    def folder(self) -> RunFolder:
        return RunFolder(self.run_dir, create=False)


def _is_run_folder(path: Path) -> bool:
    return any((path / name).exists() for name in _RUN_FILES)


def _data_for(data: Path, robot_id: int) -> Path:
    """``data`` is a split (robot<i>/ inside) or already the robot's own folder."""
    inside = robot_folder(data, robot_id)
    return inside if inside.is_dir() else data


def _own_id(run_dir: Path, data: Path | None) -> int:
    """A lone run folder's robot id: from its checkpoint, its telemetry, or its data folder's name."""
    folder = RunFolder(run_dir, create=False)
    ck = folder.load()
    if ck is not None:
        return ck.robot_id
    records = read_telemetry(folder.telemetry)
    if records:
        return records[-1].robot
    events = [e for e in read_events(folder.events) if isinstance(e.get("robot"), int)]
    if events:
        return events[-1]["robot"]
    if data is not None and data.name.startswith("robot") and data.name[5:].isdigit():
        return int(data.name[5:])
    raise DataError(f"{run_dir}: nothing written yet (no checkpoint, telemetry or events), so its robot is unknown")


def find_robots(path: Path, data: Path | None = None) -> dict[int, RobotSource]:
    """The robots of run folder ``path`` (see the module docstring), by id, in id order."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: {'not a folder' if path.exists() else 'no such folder'} (expected a run folder)")
    if (path / "robots").is_dir():  # a scenario run
        split = data or path / "data"
        ids = sorted(int(p.name) for p in (path / "robots").iterdir() if p.is_dir() and p.name.isdigit())
        if not ids:
            raise DataError(f"{path / 'robots'}: no robot run folders (robots/<id>/) yet")
        return {i: RobotSource(i, path / "robots" / str(i), _data_for(split, i)) for i in ids}
    need = "give --data: the split folder (with robot<i>/ inside) or the robot's own folder, as given to `up --data`"
    if _is_run_folder(path):
        robot_id = _own_id(path, data)
        if data is None:
            raise DataError(f"{path} is robot {robot_id}'s run folder, which does not say where its images are: {need}")
        return {robot_id: RobotSource(robot_id, path, _data_for(data, robot_id))}
    runs = {int(p.name[5:]): p for p in path.iterdir()
            if p.is_dir() and p.name.startswith("robot") and p.name[5:].isdigit() and _is_run_folder(p)}
    if not runs:
        raise DataError(f"{path}: not a run folder (no checkpoint or telemetry, no robots/<id>/ or robot<id>/ inside)")
    if data is None:
        raise DataError(f"{path} holds hand-run robots {sorted(runs)}, whose run folders do not say where their "
                        f"images are: {need}")
    return {i: RobotSource(i, runs[i], _data_for(data, i)) for i in sorted(runs)}


def _stamp(path: Path) -> tuple[int, int] | None:
    """What tells that a checkpoint was replaced (atomic rename: a new inode and mtime)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


@dataclass
class RobotModel:
    """A robot's newest model, reloaded when its checkpoint changes (it trains while we look)."""

    source: RobotSource
    trainer: RobotTrainer | None = None  # None until the first checkpoint loads
    round: int | None = None  # the checkpoint's round
    error: str | None = None  # why the newest checkpoint could not be loaded (the old model stays)
    _stamp: tuple[int, int] | None = None
    _views: dict[int | None, Views] = field(default_factory=dict)  # by training width: loaded once

    def refresh(self) -> bool:
        """Reload the checkpoint if it changed since the last look; True when the model changed."""
        folder = self.source.folder
        stamp = _stamp(folder.checkpoint)
        if stamp is None or stamp == self._stamp:
            return False
        self._stamp = stamp
        try:
            ck = folder.load(self.source.robot_id)
            if ck is None:
                return False
            width = ck.training.image_width
            if width not in self._views:
                self._views[width] = folder.load_views(self.source.data_dir, width)
            trainer = build_robot(ck.robot_id, self._views[width], ck.box_from_shared, ck.training).trainer
            load_into(trainer, folder.checkpoint, ck.trainer)
        except (CheckpointError, DataError, OSError) as e:
            self.error = " ".join(str(e).split())
            return False
        self.trainer, self.round, self.error = trainer, ck.round, None
        return True


@dataclass(frozen=True)
class RobotStatus:
    """One robot's line in the viewer's panel, from its telemetry and events."""

    robot_id: int
    round: int | None  # rounds completed (telemetry)
    psnr: float | None  # the newest PSNR on its own held-out views
    psnr_round: int | None
    frame: str  # how its frame is placed: reference / coarse / identity / unaligned (out of consensus) ...
    last_event: str | None
    done: bool

    @classmethod
    def read(cls, source: RobotSource) -> "RobotStatus":
        folder = source.folder
        records: list[RoundRecord] = read_telemetry(folder.telemetry)
        events = read_events(folder.events)
        scored = [r for r in records if r.psnr is not None]
        last = records[-1] if records else None
        return cls(source.robot_id, last.round if last else None,
                   scored[-1].psnr if scored else None, scored[-1].round if scored else None,
                   frame_state(last), str(events[-1].get("event")) if events else None, folder.done.is_file())


def frame_state(record: RoundRecord | None) -> str:
    """The robot's alignment as its log line says it (agent.telemetry.RoundRecord.log_line)."""
    if record is None:
        return "pending"
    if record.elected:
        return "reference"
    state = record.alignment or "?"
    return "unaligned (out of consensus)" if state == "unaligned" else state
