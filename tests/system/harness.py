"""Real swarms for tests: a tiny split, a swarm.toml, and one `dinerf-agent up` process per robot.

Everything is real: separate processes, Zenoh sessions on loopback, SIGKILL for faults. Only the
sizes are small (a 24x24 procedural scene, a 2^12 hash table, a few steps per round) so that a
whole swarm runs in seconds on two cores.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from agent.checkpoint import RunFolder
from agent.telemetry import RoundRecord, read_events, read_telemetry
from cli.swarm_file import free_loopback_port_base as free_port_base  # noqa: F401 (tests import it from here)

REPO = Path(__file__).resolve().parents[2]
AGENT = [sys.executable, "-m", "cli"]

TINY_TRAINING = {
    "rounds": 5,
    "steps_per_round": 8,
    "seed": 3,
    "own_holdout_every": 4,
    "consensus": {"rho0": 0.05},
    "train": {
        "rays_per_step": 256,
        "field": {"grid": {"log2_hashmap_size": 12, "num_levels": 8, "max_resolution": 128},
                  "density_hidden": 32, "color_hidden": 32},
        "occupancy": {"resolution": 32, "warmup_steps": 16, "update_every": 8},
    },
}


def merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


@dataclass
class Swarm:
    root: Path
    robots: list[int]
    procs: dict[int, subprocess.Popen] = field(default_factory=dict)
    logs: dict[int, Path] = field(default_factory=dict)

    @property
    def swarm_file(self) -> Path:
        return self.root / "swarm.toml"

    def run_dir(self, i: int) -> Path:
        return self.root / "run" / f"robot{i}"

    def start(self, i: int, extra_env: dict | None = None, extra_args: list[str] = (),
              hostile: str | None = None) -> subprocess.Popen:
        """``hostile``: an attack of tests/system/hostile.py (the real daemon with one change)."""
        log = self.root / f"robot{i}.log"
        self.logs[i] = log
        env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", **(extra_env or {}))
        program = AGENT if hostile is None else [sys.executable, str(REPO / "tests/system/hostile.py"), hostile]
        cmd = program + ["up", "--id", str(i), "--data", str(self.root / f"robot{i}"),
                         "--run-dir", str(self.run_dir(i)), *extra_args]
        p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=open(log, "a"), stderr=subprocess.STDOUT)
        self.procs[i] = p
        return p

    def start_all(self) -> None:
        for i in self.robots:
            self.start(i)

    def kill(self, i: int) -> float:
        """SIGKILL robot i; returns time.monotonic() of the kill (same clock as the robots' events)."""
        t = time.monotonic()
        self.procs[i].send_signal(signal.SIGKILL)
        self.procs[i].wait(timeout=10)
        return t

    def telemetry(self, i: int) -> list[RoundRecord]:
        return read_telemetry(RunFolder(self.run_dir(i), create=False).telemetry)

    def events(self, i: int) -> list[dict]:
        return read_events(RunFolder(self.run_dir(i), create=False).events)

    def done(self, i: int) -> dict | None:
        path = self.run_dir(i) / "done.json"
        return json.loads(path.read_text()) if path.is_file() else None

    def wait_round(self, i: int, round_index: int, timeout: float = 120) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            tel = self.telemetry(i)
            if tel and tel[-1].round >= round_index:
                return
            if self.procs[i].poll() is not None:
                raise AssertionError(f"robot {i} exited early:\n{self.log_text(i)}")
            time.sleep(0.1)
        raise AssertionError(f"robot {i} did not reach round {round_index} in {timeout} s:\n{self.log_text(i)}")

    def wait_all(self, robots: list[int] | None = None, timeout: float = 240) -> None:
        for i in robots or list(self.procs):
            try:
                code = self.procs[i].wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                raise AssertionError(f"robot {i} did not finish in {timeout} s:\n{self.log_text(i)}") from None
            assert code == 0, f"robot {i} exited with {code}:\n{self.log_text(i)}"

    def log_text(self, i: int) -> str:
        return self.logs[i].read_text()[-4000:] if i in self.logs and self.logs[i].is_file() else ""

    def stop(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
                p.wait(timeout=10)


def make_swarm(tmp: Path, robots: int = 3, topology: str = "full", frame: str = "world",
               training: dict | None = None, daemon: dict | None = None, views: int = 36, width: int = 24,
               overlap: float = 0.2, seed: int = 1, secure: bool = False, network: dict | None = None) -> Swarm:
    """Split a tiny procedural scene into robot folders and write the swarm.toml for them.

    ``secure``: a swarm CA, certificates, tls/ endpoints and access control, as `split` makes
    them; otherwise plain TCP, explicitly insecure (the rogues of these tests must get in)."""
    from agent.data.loaders import load_views
    from agent.data.split import SplitConfig, split_views, write_split
    from agent.frames import frames_of_split
    from cli.swarm_file import loopback_endpoints, security_sections, swarm_doc, write_swarm_file
    from protocol.pki import create_swarm_pki

    root = tmp / "swarm"
    result = split_views(load_views(f"procedural:views={views},width={width}"),
                         SplitConfig(robots=robots, overlap=overlap, frame=frame, seed=seed))
    write_split(result, root)
    ids = sorted(result.robots)
    daemon_cfg = {"startup_wait_s": 15.0, "round_timeout_s": 30.0, "linger_s": 1.0, "threads": 1}
    name = f"test-{os.getpid()}-{int(time.time() * 1000) % 10**6}"
    if secure:
        create_swarm_pki(root, name, ids)
    sec = security_sections(insecure=not secure)
    network = {**sec["network"], **(network or {}),
               "endpoints": loopback_endpoints(ids, free_port_base(max(ids)), tls=secure)}
    write_swarm_file(root / "swarm.toml", swarm_doc(
        name, ids, frames_of_split(frame, False), topology, network=network, security=sec["security"],
        training=merge(TINY_TRAINING, training or {}), daemon=merge(daemon_cfg, daemon or {})))
    return Swarm(root, ids)


def simulate(swarm: Swarm, overrides: list[str] = (), compression=None, robots: list[int] | None = None,
             forge=None, silent_from: dict[int, int] | None = None):
    """The in-process simulation of the same swarm (same seeds), with 1 torch thread like the daemons;
    its snapshots go through the daemons' encode/decode with ``compression`` (a CompressionConfig;
    None: the swarm file's ``[daemon.exchange]``). ``robots``: only these (the others never
    heard); ``forge(sender, round, theta) -> theta or None``: what a hostile sender sends instead;
    ``silent_from``: robot -> the first round whose snapshot nobody hears."""
    import torch

    from agent.data.folder import read_scene
    from agent.data.loaders import load_views
    from agent.swarm import Simulation
    from cli.swarm_file import load_swarm_file

    torch.set_num_threads(1)
    cfg, base = load_swarm_file(swarm.swarm_file, list(overrides))
    topo = cfg.graph()
    views = {i: load_views(swarm.root / f"robot{i}") for i in (robots or cfg.swarm.robots)}
    scene = read_scene(base / cfg.swarm.scene)
    sim = Simulation(views, {i: topo.neighbours(i) & set(views) for i in views}, scene.box_from_shared, cfg.training)
    from agent.swarm import ProtocolWire

    wire = ProtocolWire(compression or cfg.daemon.exchange, next(iter(sim.thetas.values())), list(views))
    sim.wire, sim.forge, sim.silent_from = wire, forge, dict(silent_from or {})
    sim.run()
    return sim


# --- the README's own commands, run verbatim (tests/system/test_readme_*.py) ----------------------
def readme_commands(heading: str) -> list[str]:
    """The ``dinerf-agent`` lines of the first bash block under the README's ``## heading``, in order
    (trailing ``  # comments`` dropped)."""
    import re

    text = (REPO / "README.md").read_text()
    block = re.search(rf"## {re.escape(heading)}.*?```bash\n(.*?)```", text, re.S)
    assert block, f"README has no bash block under '## {heading}'"
    return [line.split("  #")[0].strip() for line in block[1].splitlines() if line.strip().startswith("dinerf-agent ")]


def readme_env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1", COLUMNS="250")


def run_robots(argvs: dict[int, list[str]], cwd: Path, env: dict[str, str], timeout: float = 600,
               while_running=None) -> tuple[dict[int, int], dict[int, str]]:
    """One process per robot, each logging to ``cwd/robot<i>.log``; ``while_running()`` is called
    until they all end. -> (exit codes, logs). Whatever still runs at the end is killed."""
    logs = {i: open(cwd / f"robot{i}.log", "w") for i in argvs}
    procs = {i: subprocess.Popen(a, cwd=cwd, env=env, stdout=logs[i], stderr=subprocess.STDOUT)
             for i, a in argvs.items()}
    deadline = time.monotonic() + timeout
    try:
        while any(p.poll() is None for p in procs.values()) and time.monotonic() < deadline:
            if while_running is not None:
                while_running()
            else:
                time.sleep(1)
        codes = {i: p.poll() for i, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait()
        for f in logs.values():
            f.close()
    return codes, {i: (cwd / f"robot{i}.log").read_text() for i in procs}
