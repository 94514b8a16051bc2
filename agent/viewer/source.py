"""What the viewer shows of a run: each robot's newest model and its line in the panel.

Which robots a run folder holds and where their images are is agent.runs's (``open_run(...,
pending=True)``: robots still starting are shown too). The images are needed: a robot's model is
rebuilt from its checkpoint around its own views.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from agent.checkpoint import load_into, view_rows
from agent.data.views import DataError, Views
from agent.runs import RobotRun
from agent.statefile import CheckpointError
from agent.swarm import build_robot
from agent.telemetry import RoundRecord, read_events, read_telemetry
from agent.trainer import RobotTrainer

__all__ = ["RobotModel", "RobotStatus"]


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

    source: RobotRun
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
            trainer = build_robot(ck.robot_id, self._views[width], ck.box_from_shared, ck.training,
                                  view_rows=view_rows(ck.trainer)).trainer
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
    def read(cls, source: RobotRun) -> "RobotStatus":
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
