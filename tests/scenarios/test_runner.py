"""The scenario runner's orchestration, driven with a stand-in daemon (tests/scenarios/stand_in_up.py).

These tests check the timeline, kill/restart, link cuts and cleanup of the *runner*; they say
nothing about training (test_e2e.py runs the real daemon).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from cli.config import ConfigError
from cli.scenario.netns import list_namespaces
from cli.scenario.runner import ScenarioRunner
from cli.scenario.spec import load_scenario
from tests.scenarios.netns_helpers import needs_netns

TOML = """
[scenario]
name = "orchestration"
dataset = "procedural:views=24,width=16"
robots = 3
[topology]
kind = "line"
[training]
rounds = 8
steps_per_round = 1
"""


def stand_in(robot, data, swarm, run_dir, listen, connect):
    argv = [sys.executable, "-m", "tests.scenarios.stand_in_up", "up", "--id", str(robot), "--data", str(data),
            "--swarm", str(swarm), "--run-dir", str(run_dir), "--round-s", "0.25"]
    for ep in listen:
        argv += ["--listen", ep]
    for ep in connect:
        argv += ["--connect", ep]
    return argv


def spec_with(tmp_path: Path, extra: str):
    p = tmp_path / "scenario.toml"
    p.write_text(TOML + extra)
    return load_scenario(p)


def test_kill_and_restart_on_the_timeline(tmp_path):
    spec = spec_with(tmp_path, "[faults]\nkill = [{ robot = 3, round = 2 }]\nrestart = [{ robot = 3, round = 5 }]\n")
    out = tmp_path / "run"
    res = ScenarioRunner(spec, out, mode="local", up_command=stand_in, echo=lambda s: None).run()
    assert res.ok, res.reason
    run = json.loads((out / "run.json").read_text())
    faults = [e for e in run["events"] if e["event"] == "fault"]
    assert [(f["fault"], f["robot"]) for f in faults] == [("kill", 3), ("restart", 3)]
    kill, restart = faults
    assert kill["swarm_round"] >= 2 and restart["swarm_round"] >= 5
    assert min(kill["robot_rounds"].values()) == 2  # fired as soon as every robot had completed 2 rounds
    assert run["robots"]["3"]["starts"] == 2 and run["robots"]["3"]["exit_codes"][0] == -9  # SIGKILL
    rounds3 = [json.loads(l)["round"] for l in (out / "robots/3/telemetry.jsonl").read_text().splitlines()]
    assert rounds3 == sorted(set(rounds3)) and rounds3[-1] == 8  # resumed, no round twice, finished
    for i in (1, 2, 3):
        assert (out / f"robots/{i}/done.json").is_file()
    assert (out / "data/robot1/transforms.json").is_file() and (out / "swarm.toml").is_file()


def test_a_freeze_in_rounds_thaws_once_the_others_are_that_far_ahead(tmp_path):
    """Robot 1 frozen at round 2 for 3 of the others' rounds (no time limit): the thaw comes when
    robots 2 and 3 have completed 5, whatever the machine's pace, and robot 1 still finishes."""
    spec = spec_with(tmp_path, "[faults]\nfreeze = [{ robot = 1, round = 2, rounds = 3 }]\n")
    out = tmp_path / "run"
    res = ScenarioRunner(spec, out, mode="local", up_command=stand_in, echo=lambda s: None).run()
    assert res.ok, res.reason
    events = json.loads((out / "run.json").read_text())["events"]
    freeze = next(e for e in events if e.get("fault") == "freeze")
    thaw = next(e for e in events if e.get("fault") == "thaw")
    assert freeze["rounds"] == 3 and "3 rounds of the others" in freeze["description"]
    assert thaw["robot_rounds"]["1"] == freeze["robot_rounds"]["1"]  # it did nothing while frozen
    assert min(thaw["robot_rounds"][k] for k in ("2", "3")) >= freeze["robot_rounds"]["1"] + 3
    assert (out / "robots/1/done.json").is_file()


def test_a_freeze_needs_a_limit(tmp_path):
    with pytest.raises(ConfigError, match="seconds > 0 and/or rounds > 0"):
        spec_with(tmp_path, "[faults]\nfreeze = [{ robot = 1, round = 2 }]\n")


def test_link_faults_need_netns(tmp_path):
    spec = spec_with(tmp_path, "[faults]\ncut = [{ link = [1, 2], from_round = 1, to_round = 3 }]\n")
    with pytest.raises(ConfigError, match="--mode netns"):
        ScenarioRunner(spec, tmp_path / "run", mode="local", up_command=stand_in)


def test_failing_robot_stops_the_run(tmp_path):
    spec = spec_with(tmp_path, "")

    def broken(robot, *args):
        return stand_in(robot, *args) if robot != 2 else [sys.executable, "-c", "import sys; print('boom'); sys.exit(2)"]

    res = ScenarioRunner(spec, tmp_path / "run", mode="local", up_command=broken, echo=lambda s: None).run()
    assert not res.ok and "robot 2 exited with code 2: boom" in res.reason


@needs_netns
@pytest.mark.netns
def test_cut_link_in_netns_is_seen_by_the_robots(tmp_path):
    """Cut 1-2 during rounds 2..5: robot 1 hears nobody then, and hears 2 again after the heal."""
    spec = spec_with(tmp_path, '[run]\nmode = "netns"\n[faults]\ncut = [{ link = [1, 2], from_round = 2, to_round = 5 }]\n')
    out = tmp_path / "run"
    runner = ScenarioRunner(spec, out, up_command=stand_in, echo=lambda s: None)
    res = runner.run()
    assert res.ok, res.reason
    assert not [n for n in list_namespaces() if n.startswith(runner.lab.run_id)]
    recs = [json.loads(l) for l in (out / "robots/1/telemetry.jsonl").read_text().splitlines()]
    heard = {r["round"]: r["heard"] for r in recs}
    run = json.loads((out / "run.json").read_text())
    cut = next(e for e in run["events"] if e.get("fault") == "cut")
    heal = next(e for e in run["events"] if e.get("fault") == "heal")
    # robot 1's rounds that ran entirely inside the cut heard nothing; those after the heal heard robot 2
    inside = [k for k in heard if k > cut["robot_rounds"]["1"] + 1 and k <= heal["robot_rounds"]["1"]]
    after = [k for k in heard if heal["robot_rounds"]["1"] + 1 < k < 8]  # the last probe may find 2 already gone
    assert inside and after
    assert all(heard[k] == [] for k in inside), heard
    assert all(heard[k] == ["tls/198.18.0.2:7447"] for k in after), heard
    assert all(len(heard[k]) == 1 for k in heard if k < cut["robot_rounds"]["1"])
    # robot 3 (not on the cut link) always heard 2 (but in the last round: 2 may have finished)
    recs3 = [json.loads(l) for l in (out / "robots/3/telemetry.jsonl").read_text().splitlines()]
    assert all(r["heard"] == ["tls/198.18.0.5:7447"] for r in recs3[:-1]), [r["heard"] for r in recs3]


RUN_CHILD = """
import sys
from pathlib import Path
from cli.scenario.runner import ScenarioRunner
from cli.scenario.spec import load_scenario
from tests.scenarios.test_runner import stand_in
spec = load_scenario(sys.argv[1])
r = ScenarioRunner(spec, Path(sys.argv[2]), up_command=stand_in, echo=lambda s: print(s, flush=True))
res = r.run()
print('outcome', res.ok, res.reason, flush=True)
"""


@needs_netns
@pytest.mark.netns
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_signal_stops_robots_and_removes_namespaces(tmp_path, sig):
    """Ctrl-C (or SIGTERM) during a netns run: every daemon it started is gone, and every namespace."""
    import os
    import signal
    import subprocess
    import time

    (tmp_path / "scenario.toml").write_text(TOML.replace("rounds = 8", "rounds = 200") + '[run]\nmode = "netns"\n')
    out = tmp_path / "run"
    root = Path(__file__).resolve().parents[2]
    child = subprocess.Popen([sys.executable, "-c", RUN_CHILD, str(tmp_path / "scenario.toml"), str(out)], cwd=root,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 60
    while not (out / "robots/3/telemetry.jsonl").is_file() and time.monotonic() < deadline:
        time.sleep(0.2)
    namespaces = [n for n in list_namespaces() if n.startswith(f"dinerf-{child.pid}-")]
    assert len(namespaces) == 3
    pids = {}
    for ns in namespaces:
        p = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
        pids[ns] = [int(x) for x in p.stdout.split()]
    assert all(pids.values())  # a stand-in daemon runs in each
    child.send_signal(getattr(signal, sig))
    text, _ = child.communicate(timeout=60)
    assert "outcome False interrupted" in text, text
    assert not [n for n in list_namespaces() if n.startswith(f"dinerf-{child.pid}-")]
    for pid in (p for ps in pids.values() for p in ps):
        try:
            os.kill(pid, 0)
            alive = True
        except ProcessLookupError:
            alive = False
        assert not alive, f"process {pid} survived"
    run = json.loads((out / "run.json").read_text())
    assert run["ok"] is False and "interrupted" in run["reason"]
