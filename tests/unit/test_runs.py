"""agent.runs: the three run-folder layouts, where each robot's data is, and robots still starting.

The checkpoints are real ones (a tiny robot saved by agent.checkpoint.RunFolder), the data
records are written by RunFolder.write_data_record as `up` writes them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from agent.checkpoint import CheckpointError, RobotCheckpoint, RunFolder
from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box
from agent.data.views import DataError
from agent.geometry import box_from_center
from agent.runs import RobotRun, open_run
from agent.swarm import SwarmTrainingConfig, build_robot
from agent.telemetry import RoundRecord


@pytest.fixture(scope="module")
def save():
    """save(run_dir, robot_id): a real checkpoint of a tiny robot in ``run_dir``."""
    views = load_views("procedural:views=4,width=8")
    center, half, _ = estimate_scene_box(views)
    box, cfg = box_from_center(center, half), SwarmTrainingConfig()
    state = build_robot(1, views, box, cfg).trainer.state_dict()

    def write(run_dir: Path, robot_id: int) -> Path:
        RunFolder(run_dir).save(RobotCheckpoint(1, robot_id, state, False, cfg, box, "sig"))
        return run_dir
    return write


def _split(root: Path, ids: tuple[int, ...]) -> Path:
    """The folders of a split written by `dinerf-agent split`: robot<i>/, eval/ and truth.json."""
    for i in ids:
        (root / f"robot{i}").mkdir(parents=True)
    (root / "eval").mkdir()
    (root / "truth.json").write_text("{}")
    return root


def _telemetry(run_dir: Path, robot: int) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "telemetry.jsonl").write_text(RoundRecord(robot=robot, round=1).to_json() + "\n")
    return run_dir


def _fails(match: str, *args, **kwargs) -> str:
    with pytest.raises(DataError, match=match) as e:
        open_run(*args, **kwargs)
    assert "\n" not in str(e.value)  # one line for the user
    return str(e.value)


def test_a_scenario_run_its_split_and_robots_without_a_checkpoint_yet(tmp_path, save):
    out = tmp_path / "out"
    split = _split(out / "data", (1, 2))
    save(out / "robots" / "1", 1)
    (out / "robots" / "2").mkdir()  # started, nothing saved yet
    run = open_run(out)
    assert (run.kind, run.ids, run.split_dir) == ("scenario", [1], split.resolve())
    assert run.robots[1] == RobotRun(1, out / "robots" / "1", split / "robot1")
    assert run.swarm_run().run_dirs == {1: out / "robots" / "1"}
    assert open_run(out, pending=True).robots[2] == RobotRun(2, out / "robots" / "2", split / "robot2")
    with pytest.raises(DataError, match=r"no robot 3 in this run \(robots: \[1\]\)"):
        run.pick(3)
    (out / "robots" / "1" / "checkpoint.safetensors").unlink()
    _fails("robots: no robot has a checkpoint yet", out)


def test_a_swarm_run_by_hand_finds_its_data_in_the_records_or_in_data(tmp_path, save):
    split, other = _split(tmp_path / "swarm1", (3, 5)), _split(tmp_path / "copy", (3, 5))
    runs = tmp_path / "runs" / "swarm1"
    RunFolder(save(runs / "robot3", 3)).write_data_record(split / "robot3")
    RunFolder(runs / "robot5").write_data_record(split / "robot5")  # `up` started: its record, no checkpoint yet
    (runs / "robot9").mkdir()  # not a run folder: nothing in it
    run = open_run(runs)
    assert (run.kind, run.ids, run.split_dir) == ("swarm", [3], split.resolve())
    starting = open_run(runs, pending=True)  # the viewer's: no --data needed
    assert {i: r.data_dir for i, r in starting.robots.items()} == {3: (split / "robot3").resolve(),
                                                                    5: (split / "robot5").resolve()}
    given = open_run(runs, other, pending=True)  # --data wins over the records
    assert {i: r.data_dir for i, r in given.robots.items()} == {3: other / "robot3", 5: other / "robot5"}
    assert given.split_dir == other.resolve()

    (runs / "robot5" / "data.json").unlink()
    _telemetry(runs / "robot5", 5)  # an older dinerf's run folder: no record
    _fails(r"robot5: the run folder does not record its data folder .*pass --data", runs, pending=True)
    assert open_run(runs).ids == [3]  # without a checkpoint robot 5 is not part of a finished run
    (split / "robot3").rename(tmp_path / "moved")
    _fails(r"robot3: robot 3's data folder is gone \(pass --data", runs)
    (runs / "robot3" / "checkpoint.safetensors").unlink()
    _fails(r"none of its robot run dirs \[3, 5\] has a checkpoint.safetensors yet", runs)


def test_one_robots_run_dir(tmp_path, save):
    split = _split(tmp_path / "split", (4,))
    mine = save(tmp_path / "mine", 4)
    RunFolder(mine).write_data_record(split / "robot4")
    run = open_run(mine)
    assert (run.kind, run.ids, run.robots[4].data_dir) == ("robot", [4], (split / "robot4").resolve())
    assert open_run(mine, split).robots[4].data_dir == split / "robot4"  # the split: robot<id>/ inside
    assert open_run(mine, tmp_path / "own").robots[4].data_dir == tmp_path / "own"  # the robot's own folder
    assert run.split_dir == split.resolve() and open_run(mine, tmp_path / "own").split_dir is None
    with pytest.raises(DataError, match="no held-out views"):
        open_run(mine, tmp_path / "own").swarm_run()

    young = _telemetry(tmp_path / "young", 6)  # the robot id from its telemetry, its data from --data
    assert open_run(young, split, pending=True).robots == {6: RobotRun(6, young, split)}
    _fails("robot 6's run folder has no checkpoint.safetensors yet", young, split)
    fresh = tmp_path / "fresh"  # `up` has only written its record: the id from the data folder's name
    RunFolder(fresh).write_data_record(split / "robot4")
    assert open_run(fresh, pending=True).ids == [4]
    (fresh / "data.json").write_text('{"data": 3}')
    with pytest.raises(CheckpointError, match="malformed"):
        open_run(fresh, pending=True)
    (tmp_path / "empty").mkdir()
    _fails("not a run folder", tmp_path / "empty", pending=True)
    _fails("no such folder", tmp_path / "absent")
    (tmp_path / "file").write_text("x")
    _fails("not a folder", tmp_path / "file")
