"""Run a scenario: split the data, start one real ``dinerf-agent up`` per robot, apply the fault
timeline, wait for the swarm to finish, and stop everything (and every namespace) it started.

The runner only orchestrates. It knows the swarm's progress by following each robot's
``telemetry.jsonl`` (one line per completed round; its ``round`` is the number of rounds the
robot has completed, i.e. theta^round exists), and "the swarm is at round k" (counting from 0)
means every running robot has completed k rounds. Faults fire then:

- ``kill``: SIGKILL (no goodbye, like a crash or a power cut); the robot's run dir stays;
- ``restart``: the same ``up`` command again on the same run dir (the daemon resumes);
- ``freeze``: SIGSTOP, then SIGCONT after the given seconds (a hung robot that comes back);
- ``cut`` / ``netem``: :class:`cli.scenario.netns.NetnsLab` on the link, undone at ``to_round``.

The run ends when every robot that should be alive at the end has exited 0 (``done.json``), or
at ``run.timeout_s``, or at the first robot that fails on its own. Whatever happens (Ctrl-C,
SIGTERM, an exception), every process started is stopped and every namespace removed.

Output folder::

    data/                the split (robot<id>/, eval/, truth.json, scene.json ...)
    swarm.toml           what every robot was given
    robots/<id>/         each robot's run dir (telemetry.jsonl, checkpoint.safetensors, rounds/<k>.safetensors, done.json)
    logs/robot<id>.log   each robot's stdout+stderr (appended over restarts)
    run.json             timeline: starts, faults applied (wall time, swarm round), exits, outcome
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from agent.telemetry import RoundRecord
from cli.config import to_dict
from cli.swarm_file import free_loopback_port_base, security_sections, swarm_doc
from cli.scenario.spec import FreezeFault, ScenarioSpec, spec_to_dict
from cli.scenario.tomlout import dumps

__all__ = ["ScenarioRunner", "RunOutcome", "RobotProcess", "prepare_split", "free_ports", "swarm_document", "UpCommand"]

# argv of one robot's daemon, without the namespace prefix: (robot id, data dir, swarm toml, run dir, listen, connect)
UpCommand = Callable[[int, Path, Path, Path, list[str], list[str]], list[str]]


# ``python -m cli.main`` would register the commands on a second copy of the module: call main() instead
_ENTRY = "import sys; sys.argv[0] = 'dinerf-agent'; from cli.main import main; main()"


def default_up_command(robot: int, data: Path, swarm: Path, run_dir: Path, listen: list[str], connect: list[str]) -> list[str]:
    argv = [sys.executable, "-c", _ENTRY, "up", "--id", str(robot), "--data", str(data), "--swarm", str(swarm),
            "--run-dir", str(run_dir)]
    for ep in listen:
        argv += ["--listen", ep]
    for ep in connect:
        argv += ["--connect", ep]
    return argv


def free_ports(count: int) -> list[int]:
    """Free loopback ports, one per robot (``cli.swarm_file.free_loopback_port_base``)."""
    base = free_loopback_port_base(count)
    return [base + i for i in range(1, count + 1)]


def prepare_split(spec: ScenarioSpec, out: Path) -> dict:
    """Write the robot folders with ``agent.data.split`` (no shelling out); returns a summary.

    Unless the scenario is insecure, also the swarm's certificates, as `split` writes them:
    ``<out>/robot<i>/tls/``, ``<out>/monitor/`` and the CA in ``<out>/ca/`` (in no robot folder).

    With ``split.robot_image_width`` the robots get images that wide and only the held-out views
    are at the scenario's width, the resolution of the evaluation and of the centralised baseline
    (``agent.data.split.split_dataset``).
    """
    from agent.data.split import split_dataset, write_split
    from protocol.pki import create_swarm_pki

    views, result = split_dataset(spec.resolved_dataset(), spec.split, spec.width)
    write_split(result, out, overwrite=True)
    if not spec.security.insecure:  # robot<i>/tls/, monitor/ and ca/ in the split
        create_swarm_pki(out, spec.name, spec.ids,
                         robot_dirs={i: Path(out) / f"robot{i}" / spec.security.tls_dir for i in spec.ids})
    return {
        "views": len(views),
        "resolution": [result.eval_views.width, result.eval_views.height],
        "robot_resolution": [views.width, views.height],
        "robots": {rid: {"views": len(r.indices), "overlap": r.overlap} for rid, r in result.robots.items()},
        "mean_overlap": result.mean_overlap,
        "eval_views": len(result.eval_indices),
        "reference": result.reference_id,
    }


def fit_scenario(spec: ScenarioSpec, split_dir: Path) -> ScenarioSpec:
    """``spec`` with ``[training.train]`` fitted to the capture its split wrote (agent.defaults); what the
    scenario set itself stays."""
    from agent.data.folder import read_scene
    from cli.swarm_file import capture_of, fit_to_capture

    return fit_to_capture(spec, spec.given_train, capture_of(read_scene(split_dir).capture, spec.training))


def swarm_document(spec: ScenarioSpec, scene: str, endpoints: dict[int, str] | None, name: str,
                   monitor_dir: str = "data/monitor", separate_hosts: bool = False) -> dict:
    """The swarm TOML (as a dict) every robot of a scenario gets: the scenario's swarm sections,
    with per-robot snapshots always on (the report evaluates rounds/<k>.safetensors), and the
    security of :func:`prepare_split`'s certificates (``monitor_dir``: relative to the swarm file).

    ``separate_hosts``: robots in namespaces or containers of one host, whose links are emulated.
    Zenoh would pass large payloads between processes of one host through shared memory
    (/dev/shm is not namespaced): only a small reference would cross the emulated link, and
    delay/loss/bandwidth would not touch the snapshots. Measured: 0.12 MB crossed link 1-2 while
    7.4 MB of snapshots "arrived" over it. Robots on separate machines share no memory, so it is off.
    """
    sec = security_sections(spec.security.insecure, monitor_dir)
    network = {**to_dict(spec.network), **sec["network"]}
    for key in ("listen", "connect"):  # per robot, on its command line
        network.pop(key)
    if endpoints:
        network["endpoints"] = {str(k): v for k, v in endpoints.items()}
    if separate_hosts:
        network["extra"] = {"transport/shared_memory/enabled": "false", **(network.get("extra") or {})}
    security = {**to_dict(spec.security), **sec["security"]}
    return swarm_doc(name, spec.ids, spec.frames, spec.topology, scene, network=network, training=to_dict(spec.training),
                     daemon={**to_dict(spec.daemon), "keep_rounds": True}, align=to_dict(spec.align),
                     sfm=to_dict(spec.sfm), data=to_dict(spec.data), security=security)


def link_scheme(spec: ScenarioSpec, endpoints: list[str]) -> list[str]:
    """``endpoints`` over TLS unless the scenario is insecure (the namespaces' lab speaks tcp/)."""
    if spec.security.insecure:
        return list(endpoints)
    return ["tls/" + e.split("/", 1)[1] if e.startswith("tcp/") else e for e in endpoints]


@dataclass
class RobotProcess:
    """One robot's daemon as the runner sees it (across restarts)."""

    id: int
    run_dir: Path
    log_path: Path
    proc: subprocess.Popen | None = None
    starts: int = 0
    state: str = "new"  # new | running | killed | done | failed | stopped
    records: list[RoundRecord] = field(default_factory=list)
    exit_codes: list[int] = field(default_factory=list)
    _pos: int = 0
    _partial: str = ""

    @property
    def telemetry(self) -> Path:
        return self.run_dir / "telemetry.jsonl"

    def poll_telemetry(self) -> list[RoundRecord]:
        """New complete lines of telemetry.jsonl since the last call."""
        if not self.telemetry.is_file():
            return []
        with self.telemetry.open("r") as f:
            f.seek(self._pos)
            chunk = f.read()
            self._pos = f.tell()
        text = self._partial + chunk
        lines = text.split("\n")
        self._partial = lines.pop()  # an unfinished last line waits for the next call
        new = []
        for line in lines:
            if line.strip():
                with contextlib.suppress(json.JSONDecodeError, TypeError, ValueError):
                    new.append(RoundRecord.from_dict(json.loads(line)))
        self.records.extend(new)
        return new

    @property
    def completed(self) -> int:
        """Rounds this robot has completed (0 before its first telemetry line)."""
        return max((r.round for r in self.records), default=0)


@dataclass
class RunOutcome:
    ok: bool
    reason: str
    seconds: float
    out: Path
    events: list[dict]


class ScenarioRunner:
    """Runs one scenario once (see the module docstring). ``up_command`` is for tests of the runner."""

    def __init__(
        self,
        spec: ScenarioSpec,
        out: Path,
        mode: str | None = None,
        up_command: UpCommand | None = None,
        echo: Callable[[str], None] = print,
        poll_s: float = 0.2,
    ) -> None:
        self.spec = spec
        self.mode = mode or spec.run.mode
        spec.check_mode(self.mode)
        self.out = Path(out).resolve()  # the robots run with the output folder as their cwd
        self.up_command = up_command or default_up_command
        self.echo = echo
        self.poll_s = poll_s
        self.robots = {
            i: RobotProcess(i, self.out / "robots" / str(i), self.out / "logs" / f"robot{i}.log") for i in spec.ids
        }
        self.lab = None
        # frozen robots to SIGCONT: (monotonic deadline or inf, the others' round to wait for or None, robot)
        self._thaws: list[tuple[float, int | None, int]] = []
        self.events: list[dict] = []
        self.t0 = time.monotonic()
        self.endpoints: dict[int, tuple[list[str], list[str]]] = {}
        self.split_summary: dict = {}
        self._health_checked: set[tuple[int, int]] = set()
        self._health: list[tuple[int, int, subprocess.Popen]] = []  # healthchecks running: robot, start, podman

    # --- set-up -------------------------------------------------------------------------------
    def prepare(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "logs").mkdir(exist_ok=True)
        self.echo(f"[scenario] {self.spec.name}: splitting {self.spec.dataset} into {self.spec.robots} robots")
        self.split_summary = prepare_split(self.spec, self.out / "data")
        self.spec = fit_scenario(self.spec, self.out / "data")  # the settings the split's images call for
        if self.spec.record.enabled:
            from cli.scenario.recordings import record_robots

            self.split_summary["recordings"] = record_robots(self.spec, self.out / "data", self.echo)
        for r in self.robots.values():
            r.run_dir.mkdir(parents=True, exist_ok=True)

    def _swarm_toml(self, endpoints: dict[int, str] | None) -> Path:
        scene = "" if self.spec.record.enabled else "data/scene.json"  # recordings: the reference derives the box
        doc = swarm_document(self.spec, scene, endpoints, f"{self.spec.name}-{os.getpid()}-{int(time.time()) % 100000}",
                             separate_hosts=self.mode == "netns")
        path = self.out / "swarm.toml"
        path.write_text(f"# written by `dinerf-agent scenario run` for scenario {self.spec.name!r}\n" + dumps(doc))
        return path

    def _setup_network(self) -> None:
        if self.mode == "netns":
            from cli.scenario.netns import NetnsLab

            impairable = [f.link for f in self.spec.faults.netem]
            self.lab = NetnsLab(self.spec.ids, self.spec.links, impairable=impairable, impair=self.spec.run.impair,
                                log_dir=self.out / "logs")
            self.lab.create()
            self.endpoints = {i: tuple(link_scheme(self.spec, e) for e in self.lab.endpoints(i)) for i in self.spec.ids}
            self.swarm = self._swarm_toml(None)
            self._event("network", namespaces=self.lab.describe())
        elif self.mode == "compose":
            from cli.scenario.podman import ComposeLab

            self.lab = ComposeLab(self.spec, self.out, echo=self.echo)
            self.lab.create()  # docker-compose.yml and its swarm.toml, the networks and the containers
            self.endpoints = self.lab.endpoints
            self.swarm = self.out / "swarm.toml"
            self._event("network", compose=self.lab.describe())
        else:
            ports = free_ports(len(self.spec.ids))
            own = {i: link_scheme(self.spec, [f"tcp/127.0.0.1:{p}"])[0] for i, p in zip(self.spec.ids, ports)}
            topo = self.spec.graph()
            self.endpoints = {i: ([own[i]], [own[j] for j in sorted(topo.neighbours(i))]) for i in self.spec.ids}
            self.swarm = self._swarm_toml(own)

    # --- processes -----------------------------------------------------------------------------
    def _argv(self, i: int) -> list[str]:
        if self.mode == "compose":
            return self.lab.start_argv(i)
        listen, connect = self.endpoints[i]
        data = self.out / "data" / f"robot{i}"
        if self.spec.record.enabled:
            from cli.scenario.recordings import recording_of

            data = recording_of(data)  # its tls/ is beside it
        argv = self.up_command(i, data, self.swarm, self.robots[i].run_dir, listen, connect)
        if self.spec.record.replay:
            argv += ["--replay", f"{self.spec.record.replay_pace:g}"]
        return self.lab.exec_argv(i, argv) if self.lab else argv

    def _start(self, i: int) -> None:
        r = self.robots[i]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.setdefault("OMP_NUM_THREADS", str(self.spec.daemon.threads))
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        with r.log_path.open("a") as log:
            log.write(f"\n===== start {r.starts + 1} at {self._now():.1f} s: {' '.join(self._argv(i))}\n")
            log.flush()
            r.proc = subprocess.Popen(self._argv(i), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                      env=env, cwd=self.out, start_new_session=True)
        r.starts += 1
        r.state = "running"
        self._event("start", robot=i, pid=r.proc.pid, start=r.starts)
        if self.mode == "compose":
            self.lab.after_start(i, r.proc)

    def _signal(self, r: RobotProcess, sig: int) -> None:
        """A signal to robot r's daemon: to its process, or to its container (compose)."""
        with contextlib.suppress(ProcessLookupError):
            if self.mode == "compose":
                self.lab.signal(r.id, sig)
            else:
                r.proc.send_signal(sig)

    def _kill(self, i: int) -> None:
        r = self.robots[i]
        if r.proc is not None and r.proc.poll() is None:
            self._signal(r, signal.SIGKILL)  # to the daemon itself (ip netns exec execs, so it is the same pid)
            r.proc.wait(timeout=30)
            r.exit_codes.append(r.proc.returncode)
        r.state = "killed"

    def _freeze(self, i: int, fault: FreezeFault) -> None:
        r = self.robots[i]
        if r.proc is not None and r.proc.poll() is None:
            self._signal(r, signal.SIGSTOP)
            deadline = time.monotonic() + fault.seconds if fault.seconds > 0 else math.inf
            self._thaws.append((deadline, r.completed + fault.rounds if fault.rounds > 0 else None, i))

    def _others_reached(self, i: int, round_index: int | None) -> bool:
        """Every other running robot has completed ``round_index`` (or none runs any more)."""
        others = [r.completed for j, r in self.robots.items() if j != i and r.state == "running"
                  and r.proc is not None and r.proc.poll() is None]
        return round_index is not None and (not others or min(others) >= round_index)

    def _thaw_due(self, everyone: bool = False) -> None:
        due = [x for x in self._thaws if everyone or x[0] <= time.monotonic() or self._others_reached(x[2], x[1])]
        for x in due:
            self._thaws.remove(x)
            i = x[2]
            r = self.robots[i]
            if r.proc is not None and r.proc.poll() is None:
                self._signal(r, signal.SIGCONT)
                self._event("fault", fault="thaw", robot=i, description=f"SIGCONT robot {i}",
                            robot_rounds=self._robot_rounds(), how=self._how("thaw"))

    def _stop_all(self) -> None:
        """SIGTERM every running daemon, wait a little, SIGKILL what remains."""
        self._thaw_due(everyone=True)  # a stopped process would not act on SIGTERM
        running = [r for r in self.robots.values() if r.proc is not None and r.proc.poll() is None]
        for r in running:
            self._signal(r, signal.SIGTERM)
        deadline = time.monotonic() + 15
        for r in running:
            with contextlib.suppress(subprocess.TimeoutExpired):
                r.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            if r.proc.poll() is None:
                self._signal(r, signal.SIGKILL)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    r.proc.wait(timeout=20)
                if r.proc.poll() is None:
                    r.proc.kill()  # compose: the attached `podman start` itself
                    r.proc.wait(timeout=10)
            r.exit_codes.append(r.proc.returncode)
            if r.state == "running":
                r.state = "stopped"

    # --- timeline ------------------------------------------------------------------------------
    def _now(self) -> float:
        return time.monotonic() - self.t0

    def _event(self, kind: str, **info) -> None:
        self.events.append({"event": kind, "time": round(self._now(), 3), **info})

    def _timeline(self) -> list[tuple[int, int, str, Callable[[], None], dict]]:
        """(round, order, description, action, info) sorted by round; ends of windows go first."""
        f = self.spec.faults
        items = []
        for x in f.kill:
            items.append((x.round, 2, f"kill robot {x.robot}", lambda x=x: self._kill(x.robot), {"fault": "kill", "robot": x.robot}))
        for x in f.restart:
            items.append((x.round, 3, f"restart robot {x.robot}", lambda x=x: self._start(x.robot), {"fault": "restart", "robot": x.robot}))
        for x in f.freeze:
            items.append((x.round, 2, x.describe(), lambda x=x: self._freeze(x.robot, x),
                          {"fault": "freeze", "robot": x.robot, "seconds": x.seconds, "rounds": x.rounds}))
        for x in f.cut:
            a, b = x.link
            items.append((x.from_round, 1, f"cut link {a}-{b}", lambda a=a, b=b: self.lab.set_link(a, b, False), {"fault": "cut", "link": [a, b]}))
            if x.to_round is not None and x.to_round < self.spec.rounds:
                items.append((x.to_round, 0, f"heal link {a}-{b}", lambda a=a, b=b: self.lab.set_link(a, b, True), {"fault": "heal", "link": [a, b]}))
        for x in f.netem:
            a, b = x.link
            desc = f"netem on link {a}-{b}: delay {x.delay_ms:g} ms +- {x.jitter_ms:g}, loss {100 * x.loss:g}%"
            desc += f", rate {x.rate_mbit:g} Mbit/s" if x.rate_mbit else ""
            items.append((x.from_round, 1, desc, lambda x=x: self.lab.impair(*x.link, x.delay_ms, x.jitter_ms, x.loss,
                                                                             x.rate_mbit),
                          {"fault": "netem", "link": [a, b], "delay_ms": x.delay_ms, "jitter_ms": x.jitter_ms, "loss": x.loss,
                           "rate_mbit": x.rate_mbit}))
            if x.to_round is not None and x.to_round < self.spec.rounds:
                items.append((x.to_round, 0, f"clean link {a}-{b}", lambda a=a, b=b: self.lab.impair(a, b), {"fault": "netem-end", "link": [a, b]}))
        for *_, info in items:
            info["how"] = self._how(info["fault"], tuple(info["link"]) if "link" in info else None)
        return sorted(items, key=lambda t: (t[0], t[1]))

    def _how(self, fault: str, link: tuple[int, int] | None = None) -> str:
        """How a fault reaches the robots, for run.json and the report."""
        if self.mode == "compose":
            return self.lab.how(fault, link)
        if fault.startswith("netem") and link is not None and self.lab is not None:
            return "tc netem on both ends" if self.lab.impair_backend(*link) == "netem" else "the link's relay (linkemu)"
        return {"kill": "SIGKILL", "restart": "the same `up` on the same run dir", "freeze": "SIGSTOP", "thaw": "SIGCONT",
                "cut": "ip link set down on both ends", "heal": "ip link set up on both ends"}.get(fault, "")

    def _robot_rounds(self) -> dict[int, int]:
        """Rounds each robot has completed: recorded with every fault, so tests can place it."""
        return {i: r.completed for i, r in self.robots.items()}

    def swarm_round(self) -> int:
        """The round the swarm is in (from 0): the rounds every running robot has completed.

        The slowest running robot sets the pace, so a robot cut off from everybody (which trains
        alone, without waiting for anyone) cannot drag the timeline ahead of the swarm.
        """
        running = [r.completed for r in self.robots.values() if r.state == "running"]
        return min(running) if running else max((r.completed for r in self.robots.values()), default=0)

    def _expected_alive_at_end(self) -> set[int]:
        alive = set(self.spec.ids)
        for _rnd, _, kind, r in sorted([(k.round, 0, "kill", k.robot) for k in self.spec.faults.kill]
                                      + [(s.round, 1, "restart", s.robot) for s in self.spec.faults.restart]):
            (alive.discard if kind == "kill" else alive.add)(r)
        return alive

    # --- the run -------------------------------------------------------------------------------
    def run(self) -> RunOutcome:
        from cli.scenario.netns import signals_raise

        ok, reason = False, "not started"
        self.t0 = time.monotonic()
        with signals_raise():
            try:
                self.prepare()
                self._setup_network()
                for i in self.spec.ids:
                    self._start(i)
                ok, reason = self._loop()
            except KeyboardInterrupt as e:
                ok, reason = False, f"interrupted ({e or 'Ctrl-C'})"
                self.echo(f"[scenario] {reason}: stopping the robots")
            finally:
                self._collect_health(wait=True)
                self._stop_all()
                if self.lab is not None:
                    self.lab.cleanup()
                    self._event("network-removed")
        for r in self.robots.values():
            r.poll_telemetry()
        seconds = self._now()
        self._write_run_json(ok, reason, seconds)
        return RunOutcome(ok, reason, seconds, self.out, self.events)

    def _loop(self) -> tuple[bool, str]:
        pending = self._timeline()
        expected = self._expected_alive_at_end()
        deadline = self.t0 + self.spec.run.timeout_s
        seen_round = 0
        while True:
            self._thaw_due()
            self._collect_health()
            for r in self.robots.values():
                for rec in r.poll_telemetry():
                    self._progress(r.id, rec)
            rnd = self.swarm_round()
            if rnd > seen_round:
                seen_round = rnd
            while pending and pending[0][0] <= rnd:
                at, _, desc, action, info = pending.pop(0)
                self.echo(f"[scenario] round {rnd}: {desc}")
                action()
                self._event("fault", round=at, swarm_round=rnd, description=desc,
                            robot_rounds=self._robot_rounds(), **info)
            for r in self.robots.values():
                if r.state != "running" or r.proc is None or r.proc.poll() is None:
                    continue
                code = r.proc.returncode
                r.exit_codes.append(code)
                done = (r.run_dir / "done.json").is_file()
                r.state = "done" if code == 0 and done else "failed"
                self._event("exit", robot=r.id, code=code, done=done)
                if r.state == "failed":
                    tail = _tail(r.log_path)
                    return False, f"robot {r.id} exited with code {code}{': ' + tail if tail else ''}"
                self.echo(f"[scenario] robot {r.id} finished ({len(r.records)} rounds logged)")
            if all(self.robots[i].state == "done" for i in expected) and not any(
                    r.state == "running" for r in self.robots.values()):
                if pending:
                    self._event("unapplied", faults=[p[2] for p in pending])
                return True, "all robots finished"
            if time.monotonic() > deadline:
                return False, f"timeout after {self.spec.run.timeout_s:g} s (swarm at round {rnd} of {self.spec.rounds})"
            time.sleep(self.poll_s)

    def _progress(self, robot: int, rec: RoundRecord) -> None:
        line = f"[robot {robot}] round {rec.round}"
        if rec.loss is not None:
            line += f", loss {rec.loss:.4f}"
        if rec.psnr is not None:
            line += f", psnr {rec.psnr:.2f}"
        self.echo(f"{line}, heard {rec.heard}")
        start = (robot, self.robots[robot].starts)
        if self.mode == "compose" and start not in self._health_checked:  # the image's HEALTHCHECK, once per start
            self._health_checked.add(start)
            self._health.append((*start, self.lab.health_check(robot)))

    def _collect_health(self, wait: bool = False) -> None:
        """Record the healthchecks that have answered (all of them with ``wait``)."""
        for item in list(self._health):
            robot, start, proc = item
            with contextlib.suppress(subprocess.TimeoutExpired):
                out, err = proc.communicate(timeout=30 if wait else 0.001)
                self._health.remove(item)
                status = out.strip() or " ".join(err.split())[-200:] or ("healthy" if proc.returncode == 0 else "unhealthy")
                self._event("health", robot=robot, start=start, healthy=proc.returncode == 0, status=status)

    def _write_run_json(self, ok: bool, reason: str, seconds: float) -> None:
        doc = {
            "scenario": spec_to_dict(self.spec),
            "mode": self.mode,
            "ok": ok,
            "reason": reason,
            "seconds": seconds,
            "split": self.split_summary,
            "endpoints": {str(i): {"listen": l, "connect": c} for i, (l, c) in self.endpoints.items()},
            "robots": {
                str(i): {"starts": r.starts, "state": r.state, "exit_codes": r.exit_codes, "rounds_logged": len(r.records)}
                for i, r in self.robots.items()
            },
            "events": self.events,
        }
        (self.out / "run.json").write_text(json.dumps(doc, indent=2, default=str) + "\n")


def _tail(path: Path, lines: int = 1) -> str:
    try:
        text = [l for l in path.read_text(errors="replace").splitlines() if l.strip()]
    except OSError:
        return ""
    return " | ".join(text[-lines:])[:300]
