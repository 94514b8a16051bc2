"""`scenario compare`: the verdict on a fault run against its fault-free twin, from the run folders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli.scenario.compare import CompareError, compare_runs, format_comparison, rounds_lost_per_restart
from cli.scenario.spec import find_scenario, load_scenario
from tests.scenarios.test_cli import agent, one_line_error


def _jsonl(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def _run(folder: Path, psnr: dict[int, float], final_round: int = 12, starts: int = 1) -> Path:
    """A run folder as `scenario run` + `report` leave it (only the parts compare reads)."""
    from dataclasses import asdict

    spec = load_scenario(find_scenario("fault-free"))
    folder.mkdir(parents=True)
    scenario = {**asdict(spec), "path": None}
    (folder / "run.json").write_text(json.dumps({"scenario": scenario}, default=str))
    robots = {str(i): {"final_round": final_round, "starts": starts,
                       "final": {"psnr": p, "psnr_others_only": p - 2}} for i, p in psnr.items()}
    (folder / "report.json").write_text(json.dumps({"scenario": folder.name, "robots": robots, "faults": []}))
    return folder


def test_lost_rounds_are_counted_from_telemetry_and_resume_events(tmp_path):
    robot = tmp_path / "robots/3"
    _jsonl(robot / "telemetry.jsonl", [{"robot": 3, "round": k, "time": float(k)} for k in (1, 2, 3)]
           + [{"robot": 3, "round": k, "time": 10.0 + k} for k in (3, 4)])
    _jsonl(robot / "events.jsonl", [{"event": "start", "time": 0.5},
                                    {"event": "resumed", "from_round": 3, "time": 5.0},   # kept all 3
                                    {"event": "resumed", "from_round": 2, "time": 20.0}])  # lost 2
    assert rounds_lost_per_restart(robot) == [0, 2]
    with open(robot / "telemetry.jsonl", "a") as f:
        f.write('{"robot": 3, "round": 9, "ti')  # a line cut short by SIGKILL is skipped
    assert rounds_lost_per_restart(robot) == [0, 2]
    assert rounds_lost_per_restart(tmp_path / "robots/9") == []


def test_verdict_needs_every_robot_within_tolerance_and_finished(tmp_path):
    base = _run(tmp_path / "free", {1: 20.0, 2: 21.0})
    close = _run(tmp_path / "close", {1: 19.7, 2: 21.3})
    far = _run(tmp_path / "far", {1: 19.4, 2: 21.0})
    short = _run(tmp_path / "short", {1: 20.0, 2: 21.0}, final_round=11)
    c = compare_runs(close, base)
    assert c.ok and [round(r.delta_db, 2) for r in c.robots] == [-0.3, 0.3]
    assert not compare_runs(far, base).ok and compare_runs(far, base, tolerance_db=0.7).ok
    assert not compare_runs(short, base).ok
    text = format_comparison(compare_runs(far, base))
    assert "| 1 | 19.40 | 20.00 | -0.60 |" in text and "NOT met" in text


def test_cli_compare_exit_code_and_clear_errors(tmp_path):
    base = _run(tmp_path / "free", {1: 20.0})
    good = _run(tmp_path / "good", {1: 20.1})
    bad = _run(tmp_path / "bad", {1: 18.0})
    res = agent("scenario", "compare", str(good), "--fault-free", str(base), "--json", str(tmp_path / "c.json"))
    assert res.returncode == 0, res.stderr
    assert "verdict: met" in res.stdout
    assert json.loads((tmp_path / "c.json").read_text())[0]["ok"] is True
    assert agent("scenario", "compare", str(bad), "--fault-free", str(base)).returncode == 1
    res = agent("scenario", "compare", str(tmp_path / "nothing"), "--fault-free", str(base))
    assert "no report.json" in one_line_error(res)
    with pytest.raises(CompareError):
        compare_runs(tmp_path / "nothing", base)
