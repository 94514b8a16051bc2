"""docker-compose export: structure always; YAML parse and `docker-compose config` when available."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cli.scenario.compose import compose_document, dump_yaml, link_addresses, write_compose
from cli.scenario.spec import load_scenario

ROOT = Path(__file__).resolve().parents[2]

TOML = """
[scenario]
name = "ring5"
dataset = "procedural:views=40,width=16"
robots = 5
[topology]
kind = "ring"
[training]
rounds = 2
steps_per_round = 2
"""


def _spec(tmp_path: Path):
    p = tmp_path / "scenario.toml"
    p.write_text(TOML)
    return load_scenario(p)


def _parse_yaml(text: str):
    """Parse with PyYAML from this venv, else from any python3 on PATH that has it; None if neither."""
    try:
        import yaml  # type: ignore[import-not-found]

        return yaml.safe_load(text)
    except ImportError:
        pass
    for exe in {shutil.which("python3"), "/usr/bin/python3"} - {None, sys.executable}:
        if not Path(exe).exists():
            continue
        p = subprocess.run([exe, "-c", "import sys, json, yaml; print(json.dumps(yaml.safe_load(sys.stdin)))"],
                           input=text, capture_output=True, text=True)
        if p.returncode == 0:
            return json.loads(p.stdout)
    return None


def _check_structure(doc: dict, spec) -> None:
    links = spec.links
    services, networks = doc["services"], doc["networks"]
    assert sorted(services) == [f"robot{i}" for i in spec.ids]
    assert sorted(networks) == sorted(f"link-{a}-{b}" for a, b in links)
    topo = spec.graph()
    addr_of = {}
    for i in spec.ids:
        svc = services[f"robot{i}"]
        attached = set(svc["networks"])
        # only the networks of its own links
        assert attached == {f"link-{min(i, j)}-{max(i, j)}" for j in topo.neighbours(i)}
        for net, cfg in svc["networks"].items():
            addr_of[(i, net)] = cfg["ipv4_address"]
        assert svc["command"][:3] == ["up", "--id", str(i)]
        assert f"./data/robot{i}:/data/robot:ro" in svc["volumes"]
        assert svc["build"]["dockerfile"] == "Dockerfile"
        assert (Path(svc["build"]["context"]) if Path(svc["build"]["context"]).is_absolute() else None) is None
    for net, cfg in networks.items():
        assert cfg["internal"] is True
        subnet = cfg["ipam"]["config"][0]["subnet"]
        import ipaddress

        members = [(i, a) for (i, n), a in addr_of.items() if n == net]
        assert len(members) == 2  # exactly the two ends of the link
        for _, a in members:
            assert ipaddress.ip_address(a) in ipaddress.ip_network(subnet)
            assert ipaddress.ip_address(a) != ipaddress.ip_network(subnet).network_address + 1  # the gateway
    # endpoints in the commands match the static addresses: listen on own, connect to the neighbour's
    for i in spec.ids:
        cmd = services[f"robot{i}"]["command"]
        listen = {cmd[k + 1] for k, x in enumerate(cmd) if x == "--listen"}
        connect = {cmd[k + 1] for k, x in enumerate(cmd) if x == "--connect"}
        assert listen == {f"tls/{addr_of[(i, n)]}:7447" for n in services[f"robot{i}"]["networks"]}
        want = set()
        for j in topo.neighbours(i):
            net = f"link-{min(i, j)}-{max(i, j)}"
            want.add(f"tls/{addr_of[(j, net)]}:7447")
        assert connect == want


def test_structure_only_neighbours_share_a_network(tmp_path):
    spec = _spec(tmp_path)
    doc = compose_document(spec, tmp_path)
    _check_structure(doc, spec)
    assert link_addresses([(1, 2)])[(1, 2)] == {"subnet": "198.18.0.0/29", 1: "198.18.0.2", 2: "198.18.0.3"}


def test_written_files_parse_back(tmp_path):
    spec = _spec(tmp_path)
    path = write_compose(spec, tmp_path / "out" / "docker-compose.yml", with_data=True)
    doc = compose_document(spec, path.parent)
    swarm = tomllib.loads((path.parent / "swarm.toml").read_text())
    assert swarm["swarm"]["robots"] == [1, 2, 3, 4, 5] and swarm["topology"]["kind"] == "ring"
    assert swarm["swarm"]["scene"] == "scene.json" and swarm["daemon"]["keep_rounds"] is True
    for i in spec.ids:  # what the volumes mount exists, certificates included (the CA's key beside, not inside)
        assert (path.parent / f"data/robot{i}/transforms.json").is_file()
        assert {p.name for p in (path.parent / f"data/robot{i}/tls").iterdir()} == {"ca.pem", "cert.pem", "key.pem"}
    assert (path.parent / "data/ca/ca.key").is_file() and not list(path.parent.glob("data/robot*/**/ca.key"))
    assert not any("/ca" in v for s in doc["services"].values() for v in s["volumes"])  # no service mounts the CA
    assert swarm["security"]["monitor_dir"] == "data/monitor" and swarm["security"]["insecure"] is False
    assert swarm["network"]["tls_verify_name_on_connect"] is False
    assert (path.parent / "data/scene.json").is_file()
    parsed = _parse_yaml(path.read_text())
    if parsed is None:
        pytest.skip("no YAML parser (PyYAML) in this venv or on PATH: structure checked on the dict only")
    assert parsed == json.loads(json.dumps(doc))  # the YAML says exactly the document
    _check_structure(parsed, spec)


def test_yaml_quirks_roundtrip():
    doc = {"a": ["x: y", "- z", "#c", "yes", "1.0", True, 3, None, {"k": []}, []], "b": {}, "c": {"d": [{"e": 1, "f": [1, 2]}]}}
    parsed = _parse_yaml(dump_yaml(doc))
    if parsed is None:
        pytest.skip("no YAML parser available")
    assert parsed == doc


def _compose_tool() -> list[str] | None:
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if shutil.which("docker") and subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return None


@pytest.mark.skipif(_compose_tool() is None, reason="neither docker-compose nor `docker compose` is installed (Debian: apt-get install docker-compose)")
def test_docker_compose_config_accepts_it(tmp_path):
    spec = _spec(tmp_path)
    path = write_compose(spec, tmp_path / "out" / "docker-compose.yml", with_data=True)
    p = subprocess.run(_compose_tool() + ["-f", str(path), "config"], capture_output=True, text=True, cwd=path.parent)
    assert p.returncode == 0, p.stderr
    out = p.stdout
    for i in spec.ids:
        assert f"robot{i}:" in out
    assert "link-1-5" in out and "198.18.0." in out
    assert (ROOT / "Dockerfile").is_file()


def test_dockerfile_uses_the_cpu_wheel():
    text = (ROOT / "Dockerfile").read_text()
    # python:3.11-slim and the CPU index by default; build args only for a machine without a registry
    assert "ARG BASE_IMAGE=python:3.11-slim\nFROM ${BASE_IMAGE}\n" in text
    assert "ARG TORCH_SPEC=torch==2.13.0\nARG TORCH_INDEX=https://download.pytorch.org/whl/cpu\n" in text
    assert 'pip install "${TORCH_SPEC}" ${TORCH_INDEX:+--index-url "$TORCH_INDEX"}' in text
    assert 'ENTRYPOINT ["dinerf-agent"]' in text
    assert "\nUSER dinerf\n" in text and "COPY scenarios ./scenarios" in text
    assert 'HEALTHCHECK' in text and '"health", "/run/robot"' in text


def test_the_healthcheck_tells_a_progressing_robot_from_a_stuck_one(tmp_path):
    import time

    from agent.checkpoint import RunFolder
    from cli.cmd_health import run_dir_health

    run = tmp_path / "run"
    assert not run_dir_health(run, 60)[0]
    folder = RunFolder(run)
    assert run_dir_health(run, 60) == (False, f"{run}: nothing written yet")
    folder.telemetry.write_text("{}\n")
    assert run_dir_health(run, 60)[0]
    ok, why = run_dir_health(run, 60, now=time.time() + 120)
    assert not ok and "no round, event or checkpoint for 120 s" in why
    folder.write_done(1, 3, {})
    assert run_dir_health(run, 60, now=time.time() + 1e6) == (True, f"{run}: done")


def test_compose_runs_robots_as_the_host_user_with_run_dirs_made_in_advance(tmp_path):
    spec = _spec(tmp_path)
    path = write_compose(spec, tmp_path / "out" / "docker-compose.yml", with_data=True)
    doc = compose_document(spec, path.parent)
    assert all(svc["user"] == "${DINERF_UID:-1000}:${DINERF_GID:-1000}" for svc in doc["services"].values())
    assert all((path.parent / f"robots/{i}").is_dir() for i in spec.ids)  # the layout of a `scenario run`


def test_shipped_compose_files_are_current():
    """scenarios/*/docker-compose.yml are what `scenario compose` writes today (regenerate if this fails)."""
    from cli.scenario.spec import list_scenarios

    shipped = [d for d in list_scenarios() if (d / "docker-compose.yml").is_file()]
    assert shipped
    for folder in shipped:
        spec = load_scenario(folder)
        text = (folder / "docker-compose.yml").read_text()
        assert dump_yaml(compose_document(spec, folder)) in text, f"regenerate: dinerf-agent scenario compose {folder.name}"
