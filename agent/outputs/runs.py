"""Which robots a run folder holds, where their views are, and whether it has held-out views.

Three kinds of run folder are understood:

- a scenario run (``dinerf-agent scenario run``): ``robots/<id>/`` and the split in ``data/``;
- one robot's ``--run-dir`` of ``dinerf-agent up``: its ``checkpoint.safetensors`` and, since
  ``data.json`` exists, the data folder it was given. Older run folders have no record: the
  caller passes the data folder (``--data``);
- the folder of a swarm run by hand, ``runs/<swarm>/`` with ``robot<id>/`` run dirs (``up``'s
  default), each with its ``data.json``.

A split written by ``dinerf-agent split`` has the held-out views beside the robot folders
(``eval/`` and ``truth.json``): that is what ``eval`` scores against.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from agent.checkpoint import CHECKPOINT, LEGACY_CHECKPOINT, RunFolder, load_for_eval
from agent.data.views import DataError
from agent.evaluation.run import SwarmRun
from agent.trainer import RobotTrainer

__all__ = ["OutputRun", "open_run"]


@dataclass(frozen=True)
class OutputRun:
    """The robots of a run folder: run dir and data folder of each, and the split they came from."""

    path: Path
    kind: str  # "scenario", "robot" or "swarm" (robot<id>/ run dirs of a swarm run by hand)
    run_dirs: dict[int, Path]  # robot id -> its run folder
    data_dirs: dict[int, Path]  # robot id -> the folder its views were loaded from
    split_dir: Path | None  # eval/ + truth.json, when the robots' data came from a split

    @property
    def ids(self) -> list[int]:
        return sorted(self.run_dirs)

    def pick(self, robot_id: int | None) -> int:
        """``robot_id`` checked against the run's robots; None: the lowest id (the usual reference)."""
        if robot_id is None:
            return self.ids[0]
        if robot_id not in self.run_dirs:
            raise DataError(f"{self.path}: no robot {robot_id} in this run (robots: {self.ids})")
        return robot_id

    def load(self, robot_id: int, round: int | None = None, device: str | None = None) -> RobotTrainer:
        """Robot ``robot_id``'s trainer after its last round (or after ``round``), on ``device`` (default: its own)."""
        return load_for_eval(self.run_dirs[robot_id], self.data_dirs[robot_id], round=round, device=device)

    def swarm_run(self) -> SwarmRun:
        """The run as agent.evaluation sees it (needs the split)."""
        if self.split_dir is None:
            raise DataError(f"{self.path}: its data folder is not part of a split written by `dinerf-agent split` "
                            "(no eval/ and truth.json beside it): there are no held-out views to score against")
        return SwarmRun(self.split_dir, dict(self.run_dirs))


def _is_split(folder: Path) -> bool:
    """A folder written by ``dinerf-agent split``, with its held-out views and truth."""
    return (folder / "eval").is_dir() and (folder / "truth.json").is_file()


def _split_of(data_dir: Path) -> Path | None:
    """The split a robot folder belongs to (robot<i>/ beside eval/ and truth.json), if any."""
    parent = data_dir.resolve().parent
    return parent if _is_split(parent) else None


def _robot_ids(robots: Path) -> dict[int, Path]:
    found = {int(p.name): p for p in robots.iterdir() if p.is_dir() and p.name.isdigit()}
    return {i: p for i, p in found.items() if (p / CHECKPOINT).exists()}


def _hand_run(path: Path) -> OutputRun | None:
    """``path/robot<id>/`` run dirs of ``up`` (with their data records), or None when there are none."""
    found = {int(p.name[5:]): p for p in path.glob("robot*")
             if p.name[5:].isdigit() and (p / CHECKPOINT).exists()}
    if not found:
        return None
    data_dirs = {}
    for i, run_dir in found.items():
        recorded = RunFolder(run_dir, create=False).recorded_data_dir()
        if recorded is None:
            raise DataError(f"{run_dir}: the run folder does not record its data folder (an older dinerf): "
                            "give that robot's run dir and its --data instead")
        data_dirs[i] = recorded
    splits = {_split_of(d) for d in data_dirs.values()}
    return OutputRun(path, "swarm", found, data_dirs, splits.pop() if len(splits) == 1 else None)


def open_run(path: str | Path, data: str | Path | None = None) -> OutputRun:
    """The run folder at ``path`` (see the module docstring); ``data``: a robot run's data folder, if unrecorded."""
    path = Path(path)
    if not path.is_dir():
        raise DataError(f"{path}: {'not a folder' if path.exists() else 'no such folder'} "
                        "(expected a scenario run folder or a robot's --run-dir)")
    if (path / "robots").is_dir() and (path / "data").is_dir():
        run_dirs = _robot_ids(path / "robots")
        if not run_dirs:
            raise DataError(f"{path}/robots: no robot has a checkpoint yet")
        split = path / "data"
        data_dirs = {i: split / f"robot{i}" for i in run_dirs}
        return OutputRun(path, "scenario", run_dirs, data_dirs, split if _is_split(split) else None)
    folder = RunFolder(path, create=False)
    ck = folder.load()  # CheckpointError for a damaged or foreign file
    if ck is None and data is None:
        hand = _hand_run(path)
        if hand is not None:
            return hand
    if ck is None:
        legacy = " (an older dinerf's checkpoint.pt is not loaded)" if (path / LEGACY_CHECKPOINT).exists() else ""
        raise DataError(f"{path}: not a run folder: no {CHECKPOINT}, no robots/ + data/ of a scenario run "
                        f"and no robot<id>/ run dirs{legacy}")
    data_dir = Path(data) if data is not None else folder.recorded_data_dir()
    if data_dir is None:
        raise DataError(f"{path}: the run folder does not record its data folder (an older dinerf): pass --data")
    if not data_dir.exists():
        raise DataError(f"{data_dir}: the robot's data folder is gone (pass --data to give it)")
    return OutputRun(path, "robot", {ck.robot_id: path}, {ck.robot_id: data_dir}, _split_of(data_dir))
