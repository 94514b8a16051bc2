"""Scenarios as containers: the compose file's link services, the build's pip configuration, the
one-line errors; and, where podman runs (root, podman-compose >= 1.1), a real compose swarm.

The slow runs build the image first (from the layer cache after the first build; the first one
on a fresh machine makes the Debian base with debootstrap and installs torch: minutes).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from cli.scenario.compose import compose_document, dump_yaml, static_impairments, write_compose
from cli.scenario.podman import compose_unavailable_reason
from cli.scenario.spec import find_scenario, load_scenario
from tests.agent_cli import agent
from tests.scenarios.test_cli import one_line_error
from tests.scenarios.test_compose import _parse_yaml

_REASON = compose_unavailable_reason()
needs_podman = pytest.mark.skipif(_REASON is not None, reason=f"container runs skipped: {_REASON}")

CAPPED = """
[scenario]
name = "capped-line"
dataset = "procedural:views=24,width=24"
robots = 3
[topology]
kind = "line"
[training]
rounds = 4
[faults]
netem = [{ link = [1, 2], from_round = 0, rate_mbit = 20 },
         { link = [2, 3], from_round = 1, to_round = 3, delay_ms = 50, loss = 0.1 }]
kill = [{ robot = 3, round = 1 }]
"""


def test_links_impaired_for_the_whole_run_are_in_the_compose_file(tmp_path):
    (tmp_path / "scenario.toml").write_text(CAPPED)
    spec = load_scenario(tmp_path)
    assert [f.link for f in static_impairments(spec)] == [(1, 2)]  # the other has a time: the runner's
    doc = compose_document(spec, tmp_path)
    assert sorted(doc["services"]) == ["robot1", "robot1-links", "robot2", "robot2-links", "robot3"]
    for i, addr in ((1, "198.18.0.2"), (2, "198.18.0.3")):
        svc = doc["services"][f"robot{i}-links"]
        assert svc["network_mode"] == f"service:robot{i}" and svc["cap_add"] == ["NET_ADMIN"]
        assert svc["user"] == "0:0" and svc["depends_on"] == [f"robot{i}"]  # the robot itself stays unprivileged
        script = svc["entrypoint"][2]
        # netem with its rate, or tbf where the kernel has no netem; on robot i's address on link 1-2
        assert f"qdisc {addr} netem delay 0.0ms rate 20.0mbit || qdisc {addr} tbf rate 20mbit" in script
        assert "$$dev" in script and "$dev" not in script.replace("$$", "")  # compose would substitute $dev
    assert "198.18.0.10" not in doc["services"]["robot2-links"]["entrypoint"][2]  # link 2-3 is not impaired from 0
    parsed = _parse_yaml(dump_yaml(doc))
    if parsed is not None:
        assert parsed == json.loads(json.dumps(doc))


def test_the_compose_file_says_which_faults_the_runner_applies(tmp_path):
    (tmp_path / "scenario.toml").write_text(CAPPED)
    out = write_compose(load_scenario(tmp_path), tmp_path / "c" / "docker-compose.yml")
    head = [l for l in out.read_text().splitlines() if l.startswith("#")]
    assert any("robot<i>-links services" in l for l in head)
    assert any("from outside" in l and "1 kill, 1 netem" in l for l in head), head
    swarm = (out.parent / "swarm.toml").read_text()
    assert '"transport/shared_memory/enabled" = "false"' in swarm  # containers share no memory, as machines


def test_the_build_takes_the_hosts_pip_configuration(tmp_path, monkeypatch):
    from cli.scenario.images import CPU_INDEX, _torch_index, host_pip_config

    wheels, index = tmp_path / "wheels", tmp_path / "pypi" / "simple"
    wheels.mkdir()
    index.mkdir(parents=True)
    conf = tmp_path / "pip.conf"
    conf.write_text(f"[global]\nfind-links = {wheels}\nextra-index-url = file://{index}\n")
    for key in [k for k in os.environ if k.startswith("PIP_")]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("PIP_CONFIG_FILE", str(conf))
    monkeypatch.setenv("PIP_DEFAULT_TIMEOUT", "77")
    text, paths = host_pip_config()
    assert f"find-links = {wheels}" in text and "default-timeout = 77" in text
    assert wheels in paths and index.parent in paths  # an index's pages link to files beside it
    assert _torch_index(paths) == CPU_INDEX  # no torch wheel at hand: the CPU index
    (wheels / "torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl").write_bytes(b"")
    assert _torch_index(paths) == ""  # the host's pip has one: pip's configuration


def test_compose_mode_without_podman_is_a_one_line_error(tmp_path):
    bindir = tmp_path / "bin"  # a PATH with no podman
    bindir.mkdir()
    p = agent("scenario", "run", "quickstart", "--mode", "compose", "--out", str(tmp_path / "o"),
              env={"PATH": str(bindir)})
    assert "--mode compose: podman is not installed" in one_line_error(p)
    assert not (tmp_path / "o").exists()
    assert "mode must be local, netns or compose" in one_line_error(agent("scenario", "run", "quickstart", "--mode", "vm"))


# --- for real ---------------------------------------------------------------------------------

TINY = ["--set", "training.steps_per_round=5", "--set", "baseline.enabled=false", "--set", "report.orbit_frames=0",
        "--set", "report.render_views=1", "--set", "report.own_views_every=0", "--set", "report.ssim=false"]


def _left_behind(project: str) -> list[str]:
    label = f"label=io.podman.compose.project={project}"
    ps = subprocess.run(["podman", "ps", "-aq", "--filter", label], capture_output=True, text=True).stdout.split()
    nets = subprocess.run(["podman", "network", "ls", "-q", "--filter", label], capture_output=True, text=True).stdout
    return ps + nets.split()


def _run(tmp_path: Path, name: str, *args: str) -> tuple[dict, Path]:
    out = tmp_path / name
    p = agent("scenario", "run", name, "--mode", "compose", "--out", str(out), *TINY, *args, timeout=1200)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    doc = json.loads((out / "run.json").read_text())
    assert doc["mode"] == "compose" and doc["ok"], doc["reason"]
    project = next(e for e in doc["events"] if e["event"] == "network")["compose"]["project"]
    assert _left_behind(project) == []  # containers and networks removed
    return doc, out


def _rounds(out: Path, robot: int) -> list[int]:
    """The rounds robot's telemetry logged."""
    lines = (out / "robots" / str(robot) / "telemetry.jsonl").read_text().splitlines()
    return sorted({json.loads(l)["round"] for l in lines if l.strip()})


@pytest.mark.slow
@needs_podman
def test_quickstart_as_containers(tmp_path):
    doc, out = _run(tmp_path, "quickstart", "--set", "training.rounds=2")
    spec = load_scenario(find_scenario("quickstart"))
    for i in spec.ids:
        r = doc["robots"][str(i)]
        assert r["state"] == "done" and r["exit_codes"] == [0] and _rounds(out, i) == [1, 2]
        assert (out / "robots" / str(i) / "done.json").is_file()
        assert os.stat(out / "robots" / str(i) / "done.json").st_uid != 0  # written by the image's user
    health = [e for e in doc["events"] if e["event"] == "health"]
    assert sorted(e["robot"] for e in health) == spec.ids and all(e["healthy"] for e in health), health
    report = json.loads((out / "report.json").read_text())
    assert report["mode"] == "compose" and (out / "report.md").is_file()
    assert all(report["robots"][str(i)]["final"]["psnr"] > 5 for i in spec.ids)
    assert report["links_bytes"]["1->2"] > 0  # snapshots crossed the link networks


@pytest.mark.slow
@needs_podman
def test_kill_and_restart_a_robot_container(tmp_path):
    doc, out = _run(tmp_path, "fault-kill-restart", "--set", "training.rounds=5", "--set", "training.steps_per_round=10",
                    "--no-report", "--set", "faults.kill=[{robot=3,round=1}]", "--set", "faults.restart=[{robot=3,round=2}]")
    robot3 = doc["robots"]["3"]
    assert robot3["starts"] == 2 and robot3["exit_codes"][0] == 137 and robot3["state"] == "done"  # SIGKILLed, back
    faults = {e["fault"]: e for e in doc["events"] if e["event"] == "fault"}
    assert faults["kill"]["how"] == "runner: podman kill (SIGKILL)" and faults["kill"]["robot_rounds"]["3"] < 5
    assert faults["restart"]["how"].startswith("runner: podman start")
    for i in (1, 2, 3, 4):  # every robot to the last round (robot 3 joins the swarm's round when back)
        done = json.loads((out / "robots" / str(i) / "done.json").read_text())
        assert doc["robots"][str(i)]["state"] == "done" and done["rounds"] == 5
    log = (out / "logs" / "robot3.log").read_text()
    assert "resumed from /run/robot/checkpoint.safetensors" in log  # the same run dir, in the same container
