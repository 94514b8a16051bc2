"""Which robots a run folder holds and where their views are: the one place every command finds them.

Three kinds of run folder are understood:

- a scenario run (``dinerf-agent scenario run``): ``robots/<id>/`` and the split in ``data/``;
- one robot's ``--run-dir`` of ``dinerf-agent up``;
- the folder of a swarm run by hand, ``runs/<swarm>/`` with ``robot<id>/`` run dirs (``up``'s default).

A robot's data folder is ``--data`` when the caller gives it (the split folder with ``robot<i>/``
inside, or the robot's own folder); else the one ``up`` recorded in ``data.json``; a scenario's is
in its ``data/``. Older run folders have no record: the caller then passes ``--data``.

``render``/``eval``/``export`` need a checkpoint: robots without one are not part of the run. The
viewer asks for ``pending`` robots too (run folders with nothing but telemetry, events or their
data record yet): a swarm that is still starting.

A split written by ``dinerf-agent split`` has the held-out views beside the robot folders
(``eval/`` and ``truth.json``): that is what ``eval`` scores against.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from agent.checkpoint import CHECKPOINT, DATA_RECORD, EVENTS, LEGACY_CHECKPOINT, TELEMETRY, RunFolder, load_robot
from agent.data.split import robot_folder
from agent.data.views import DataError
from agent.evaluation.run import SwarmRun
from agent.swarm import RobotSetup
from agent.telemetry import read_events, read_telemetry
from agent.trainer import RobotTrainer

__all__ = ["RobotRun", "Run", "open_run"]

_RUN_FILES = (CHECKPOINT, LEGACY_CHECKPOINT, TELEMETRY, EVENTS, DATA_RECORD)  # any of them: a robot's run folder
NEED_DATA = "pass --data: the split folder (with robot<i>/ inside) or the robot's own folder, as given to `up --data`"


@dataclass(frozen=True)
class RobotRun:
    """One robot of a run: its run folder and the folder of its views."""

    robot_id: int
    run_dir: Path
    data_dir: Path

    @property
    def folder(self) -> RunFolder:
        return RunFolder(self.run_dir, create=False)


@dataclass(frozen=True)
class Run:
    """The robots of a run folder, by id in id order, and the split their data came from."""

    path: Path
    kind: str  # "scenario", "robot" or "swarm" (robot<id>/ run dirs of a swarm run by hand)
    robots: dict[int, RobotRun]
    split_dir: Path | None  # eval/ + truth.json, when the robots' data came from a split

    @property
    def ids(self) -> list[int]:
        return list(self.robots)

    @property
    def run_dirs(self) -> dict[int, Path]:
        return {i: r.run_dir for i, r in self.robots.items()}

    def pick(self, robot_id: int | None) -> int:
        """``robot_id`` checked against the run's robots; None: the lowest id (the usual reference)."""
        if robot_id is None:
            return self.ids[0]
        if robot_id not in self.robots:
            raise DataError(f"{self.path}: no robot {robot_id} in this run (robots: {self.ids})")
        return robot_id

    def load(self, robot_id: int, round: int | None = None, device: str | None = None) -> RobotTrainer:
        """Robot ``robot_id``'s trainer after its last round (or after ``round``), on ``device`` (default: its own)."""
        return self.load_setup(robot_id, round, device).trainer

    def load_setup(self, robot_id: int, round: int | None = None, device: str | None = None) -> RobotSetup:
        """As :meth:`load`, with the robot's own held-out views (``training.own_holdout_every``)."""
        robot = self.robots[robot_id]
        return load_robot(robot.run_dir, robot.data_dir, round=round, device=device)

    def swarm_run(self) -> SwarmRun:
        """The run as agent.evaluation sees it (needs the split)."""
        if self.split_dir is None:
            raise DataError(f"{self.path}: its data folder is not part of a split written by `dinerf-agent split` "
                            "(no eval/ and truth.json beside it): there are no held-out views to score against")
        return SwarmRun(self.split_dir, self.run_dirs, {i: r.data_dir for i, r in self.robots.items()})


def _is_split(folder: Path) -> bool:
    """A folder written by ``dinerf-agent split``, with its held-out views and truth."""
    return (folder / "eval").is_dir() and (folder / "truth.json").is_file()


def _split_of(data_dirs: list[Path]) -> Path | None:
    """The one split the robot folders belong to (robot<i>/ beside eval/ and truth.json, or a recording
    inside robot<i>/, as a recording scenario's), if any."""
    for up in (1, 2):
        parents = {d.resolve().parents[up - 1] for d in data_dirs}
        parent = parents.pop() if len(parents) == 1 else None
        if parent is not None and _is_split(parent):
            return parent
    return None


def _is_run_folder(path: Path) -> bool:
    return any((path / name).exists() for name in _RUN_FILES)


def _has_checkpoint(run_dir: Path) -> bool:
    return (run_dir / CHECKPOINT).exists() or (run_dir / LEGACY_CHECKPOINT).exists()  # the old one: refused on load


def _data_for(run_dir: Path, robot_id: int, data: Path | None) -> Path:
    """Robot ``robot_id``'s data folder: ``data`` (a split, or already its own folder), else the recorded one."""
    if data is not None:
        inside = robot_folder(data, robot_id)
        return inside if inside.is_dir() else data
    recorded = RunFolder(run_dir, create=False).recorded_data_dir()
    if recorded is None:
        raise DataError(f"{run_dir}: the run folder does not record its data folder (an older dinerf): {NEED_DATA}")
    if not recorded.exists():
        raise DataError(f"{recorded}: robot {robot_id}'s data folder is gone ({NEED_DATA})")
    return recorded


def _own_id(run_dir: Path, data: Path | None) -> int:
    """A lone run folder's robot id: from its checkpoint, telemetry, events, or its data folder's name."""
    folder = RunFolder(run_dir, create=False)
    ck = folder.load()  # CheckpointError for a damaged, foreign or pickled one
    if ck is not None:
        return ck.robot_id
    records = read_telemetry(folder.telemetry)
    if records:
        return records[-1].robot
    events = [e for e in read_events(folder.events) if isinstance(e.get("robot"), int)]
    if events:
        return events[-1]["robot"]
    named = data if data is not None else folder.recorded_data_dir()
    if named is not None and named.name.startswith("robot") and named.name[5:].isdigit():
        return int(named.name[5:])
    raise DataError(f"{run_dir}: nothing written yet (no checkpoint, telemetry or events), so its robot is unknown")


def _numbered(folder: Path, prefix: str) -> dict[int, Path]:
    """``folder/<prefix><id>/`` sub-folders by id."""
    return {int(p.name[len(prefix):]): p for p in folder.iterdir()
            if p.is_dir() and p.name.startswith(prefix) and p.name[len(prefix):].isdigit()}


def _run(path: Path, kind: str, run_dirs: dict[int, Path], data_of) -> Run:
    robots = {i: RobotRun(i, run_dirs[i], data_of(i)) for i in sorted(run_dirs)}
    return Run(path, kind, robots, _split_of([r.data_dir for r in robots.values()]))


def open_run(path: str | Path, data: str | Path | None = None, pending: bool = False) -> Run:
    """The run folder at ``path`` (see the module docstring).

    data: the robots' data folder (``--data``), for run folders that do not record theirs.
    pending: robots without a checkpoint yet are part of the run too (the viewer's: a swarm starting)."""
    path, data = Path(path), None if data is None else Path(data)
    if not path.is_dir():
        raise DataError(f"{path}: {'not a folder' if path.exists() else 'no such folder'} "
                        "(expected a run folder: a scenario's --out, up's runs/<swarm>/ or one robot's --run-dir)")
    if (path / "robots").is_dir():  # a scenario run
        split = data if data is not None else path / "data"
        if not split.is_dir():
            raise DataError(f"{path}: a scenario run folder without its data/ split ({NEED_DATA})")
        run_dirs = {i: p for i, p in _numbered(path / "robots", "").items() if pending or _has_checkpoint(p)}
        if not run_dirs:
            raise DataError(f"{path / 'robots'}: no robot has {'a run folder (robots/<id>/)' if pending else 'a checkpoint'}"
                            " yet")
        return _run(path, "scenario", run_dirs, lambda i: _data_for(run_dirs[i], i, split))
    if _is_run_folder(path):  # one robot's --run-dir
        robot_id = _own_id(path, data)
        if not pending and not _has_checkpoint(path):
            raise DataError(f"{path}: robot {robot_id}'s run folder has no {CHECKPOINT} yet")
        return _run(path, "robot", {robot_id: path}, lambda i: _data_for(path, i, data))
    runs = {i: p for i, p in _numbered(path, "robot").items() if _is_run_folder(p)}
    if not runs:
        raise DataError(f"{path}: not a run folder (no {CHECKPOINT}, telemetry or {DATA_RECORD}, no robots/<id>/ "
                        "of a scenario run, no robot<id>/ run dirs inside)")
    run_dirs = {i: p for i, p in runs.items() if pending or _has_checkpoint(p)}
    if not run_dirs:
        raise DataError(f"{path}: none of its robot run dirs {sorted(runs)} has a {CHECKPOINT} yet")
    return _run(path, "swarm", run_dirs, lambda i: _data_for(run_dirs[i], i, data))
