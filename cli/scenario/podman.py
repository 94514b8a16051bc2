"""A scenario's compose file run for real: robots as podman containers, faults from outside.

``dinerf-agent scenario run NAME --mode compose`` writes the scenario's ``docker-compose.yml``
into the run folder (:mod:`cli.scenario.compose`: one service per robot, one internal network per
topology link with static addresses, and a ``robot<i>-links`` service per robot with a link
impaired for the whole run), has ``podman-compose up --no-start`` create the networks and the
containers, then plays the timeline on them. A container is started with
``podman start --attach``: that process stands for the robot (its output is the robot's log, its
exit code the daemon's), so the runner treats it as it treats a local daemon.

What compose cannot say, the runner does from outside (and ``run.json``/the report say so):

- kill: ``podman kill`` (SIGKILL); restart: ``podman start`` of the same container (same
  command, same run dir: the daemon resumes); freeze: ``podman pause`` / ``unpause``;
- cut: ``ip link set down`` on both ends, in the containers' network namespaces (``nsenter``);
- netem for some rounds: ``tc qdisc`` on both ends there too (``netem``; a rate cap alone is
  ``tbf`` on kernels without ``sch_netem``). A container's namespace is new at every start, so
  what the runner applied is applied again after a restart.

The image's HEALTHCHECK is run once per start of a robot (``podman healthcheck run``, recorded
in ``run.json``): without systemd podman cannot time it, so containers are made without the timer.

Containers need a rootful podman (bridges with static addresses, ``tc`` in their namespaces),
``podman-compose`` >= 1.1 (1.0.x gives one ``--ip`` for all networks, containers/podman-compose
#817; tested with 1.6.0) and, where ``crun`` cannot set the default rlimits (as on this project's
VMs), ``runc`` with the limits of :data:`ULIMITS`. Robots run as the image's user (uid 1000):
their folders are handed to it before the start.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from cli.scenario.spec import ScenarioSpec

__all__ = ["PodmanError", "ComposeLab", "compose_unavailable_reason", "compose_tool", "container_flags", "podman",
           "cleanup_stale_projects", "ROBOT_UID"]

ROBOT_UID = 1000  # the Dockerfile's user
# Within the hard limits of an unprivileged sandbox (podman's defaults are above them there).
ULIMITS = ("nofile=1024:1024", "nproc=4096:4096")
MIN_COMPOSE = (1, 1)


class PodmanError(RuntimeError):
    """A podman or podman-compose command failed (the message holds its stderr)."""


def podman(*args: str, check: bool = True, timeout: float = 120.0, **kw) -> subprocess.CompletedProcess:
    try:
        p = subprocess.run(["podman", *args], capture_output=True, text=True, timeout=timeout, **kw)
    except FileNotFoundError:
        raise PodmanError("podman is not installed (Debian: apt-get install podman)") from None
    except subprocess.TimeoutExpired:
        raise PodmanError(f"podman {' '.join(args)}: timed out after {timeout:g} s") from None
    if check and p.returncode != 0:
        raise PodmanError(f"podman {' '.join(args[:3])}... failed: {_last_error(p.stderr or p.stdout)}")
    return p


def _last_error(text: str) -> str:
    """The line that says what went wrong (podman prints systemd noise before it on these VMs)."""
    lines = [l for l in text.strip().splitlines() if l.strip() and "systemd" not in l]
    return lines[-1].strip() if lines else text.strip()[-300:]


def container_flags(create: bool = False) -> list[str]:
    """``podman build`` (and with ``create``, ``podman create``) flags this machine needs: runc
    where installed (crun cannot set the rlimits in this project's sandboxes), rlimits inside the
    hard limits, and without systemd no healthcheck timer (podman makes them with systemd; the
    runner runs the HEALTHCHECK itself)."""
    flags = ["--runtime", "runc"] if shutil.which("runc") else []
    for limit in ULIMITS:
        flags += ["--ulimit", limit]
    if create and not Path("/run/systemd/system").is_dir():
        flags += ["--health-interval", "disable"]
    return flags


def _version(text: str) -> tuple[int, ...]:
    m = re.search(r"(\d+)\.(\d+)(?:\.(\d+))?", text)
    return tuple(int(x) for x in m.groups() if x is not None) if m else ()


def compose_tool() -> tuple[list[str] | None, str]:
    """(argv of a podman-compose recent enough, or None; what was found, for the error)."""
    found = []
    with contextlib.suppress(ImportError):
        import podman_compose  # type: ignore[import-not-found]

        v = _version(getattr(podman_compose, "__version__", ""))
        if v >= MIN_COMPOSE:
            return [sys.executable, "-m", "podman_compose"], ""
        found.append(f"podman_compose {'.'.join(map(str, v))} in this Python")
    exe = shutil.which("podman-compose")
    if exe:
        with contextlib.suppress(OSError, subprocess.TimeoutExpired):
            out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=30).stdout
            v = _version(out.split("podman-compose", 1)[-1] if "podman-compose" in out else out)
            if v >= MIN_COMPOSE:
                return [exe], ""
            found.append(f"{exe} {'.'.join(map(str, v))}")
    return None, ", ".join(found) or "none"


def compose_unavailable_reason() -> str | None:
    """None when compose runs can be made here, else why not (for a one-line error or a skip)."""
    if sys.platform != "linux":
        return "container runs need Linux"
    if shutil.which("podman") is None:
        return "podman is not installed (Debian: apt-get install podman)"
    if os.geteuid() != 0:
        return "container runs need root (rootful podman: link networks with static addresses, tc in the robots' namespaces)"
    tool, found = compose_tool()
    if tool is None:
        return (f"no podman-compose >= {'.'.join(map(str, MIN_COMPOSE))} (found: {found}; Debian's 1.0.x cannot give a "
                "container one address per network): pip install 'podman-compose>=1.1'")
    return None


def cleanup_stale_projects(force: bool = False) -> list[str]:
    """Remove the containers, networks and pods of compose runs (``dinerf-<pid>-<hex>``) whose
    runner is gone (all of them with ``force``); returns the projects removed."""
    label = "io.podman.compose.project"
    projects = {c["Labels"].get(label) for c in json.loads(podman("ps", "-a", "--format", "json").stdout or "[]")
                if c.get("Labels")}
    projects |= {n.get("labels", {}).get(label) for n in json.loads(podman("network", "ls", "--format", "json").stdout or "[]")}
    removed = []
    for project in sorted(p for p in projects if p and re.fullmatch(r"dinerf-\d+-[0-9a-f]+", p)):
        pid = int(project.split("-")[1])
        if not force and (pid == os.getpid() or _alive(pid)):
            continue
        for ident in podman("ps", "-aq", "--filter", f"label={label}={project}", check=False).stdout.split():
            podman("rm", "-f", ident, check=False)
        for ident in podman("network", "ls", "-q", "--filter", f"label={label}={project}", check=False).stdout.split():
            podman("network", "rm", "-f", ident, check=False)
        podman("pod", "rm", "-f", f"pod_{project}", check=False)
        removed.append(project)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class ComposeLab:
    """The containers and networks of one compose run (see the module docstring).

    The same role as :class:`cli.scenario.netns.NetnsLab` for the runner: made by :meth:`create`,
    faults by :meth:`signal`, :meth:`set_link`, :meth:`impair`, removed by :meth:`cleanup`.
    """

    def __init__(self, spec: ScenarioSpec, out: Path, echo: Callable[[str], None] = print,
                 image: str | None = None) -> None:
        from cli.scenario.compose import IMAGE

        self.spec = spec
        self.out = Path(out)
        self.echo = echo
        self.image = image or IMAGE
        self.project = f"dinerf-{os.getpid()}-{secrets.token_hex(2)}"
        self.compose_file = self.out / "docker-compose.yml"
        self.containers: dict[str, str] = {}  # service -> container name
        self.endpoints: dict[int, tuple[list[str], list[str]]] = {}
        self.link_state: dict[tuple[int, int], dict] = {}
        self.sidecars: dict[str, dict] = {}  # the compose file's robot<i>-links services
        self._tool: list[str] = []
        self._closed = False
        self.created = False

    # --- building ----------------------------------------------------------------------------
    def create(self) -> "ComposeLab":
        from cli.scenario.compose import compose_document, link_addresses, robot_command, write_compose

        from cli.scenario.netns import netem_available

        reason = compose_unavailable_reason()
        if reason:
            raise PodmanError(reason)
        if any(f.delay_ms or f.loss for f in self.spec.faults.netem) and not netem_available():
            raise PodmanError("this kernel has no sch_netem (tc ... netem fails): delay and loss on container links "
                              "need it; --mode netns emulates them with its relay (a rate cap alone works here, with tbf)")
        self._tool, _ = compose_tool()
        write_compose(self.spec, self.compose_file, image=self.image)
        doc = compose_document(self.spec, self.out, image=self.image)
        for i in self.spec.ids:
            cmd = robot_command(self.spec, i, link_addresses(self.spec.links))
            self.endpoints[i] = ([cmd[k + 1] for k, x in enumerate(cmd) if x == "--listen"],
                                 [cmd[k + 1] for k, x in enumerate(cmd) if x == "--connect"])
        self.link_state = {key: {"up": True, "impair": None} for key in link_addresses(self.spec.links)}
        self.sidecars = {s: svc for s, svc in doc["services"].items() if s.endswith("-links")}
        self._hand_to_robot_user()
        atexit.register(self.cleanup)
        try:
            self._compose("up", "--no-start", "--no-build")
            self.containers = self._container_names()
            missing = sorted(set(doc["services"]) - set(self.containers))
            if missing:
                raise PodmanError(f"podman-compose made no container for {', '.join(missing)}")
            self.created = True
        except BaseException:
            self.cleanup()
            raise
        return self

    def _compose(self, *args: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
        env = dict(os.environ, DINERF_UID=str(ROBOT_UID), DINERF_GID=str(ROBOT_UID))
        argv = [*self._tool, "-p", self.project, "-f", str(self.compose_file),
                "--podman-run-args", " ".join(container_flags(create=True)), *args]
        try:
            p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=env, cwd=self.out)
        except subprocess.TimeoutExpired:
            raise PodmanError(f"podman-compose {' '.join(args)}: timed out after {timeout:g} s") from None
        with (self.out / "logs" / "compose.log").open("a") as log:
            log.write(f"$ {' '.join(argv)}\n{p.stdout}{p.stderr}\n")
        if p.returncode != 0:
            raise PodmanError(f"podman-compose {' '.join(args)} failed: {_last_error(p.stderr or p.stdout)}")
        return p

    def _container_names(self) -> dict[str, str]:
        p = podman("ps", "-a", "--filter", f"label=io.podman.compose.project={self.project}", "--format", "json")
        return {c["Labels"]["io.podman.compose.service"]: c["Names"][0] for c in json.loads(p.stdout or "[]")}

    def _hand_to_robot_user(self) -> None:
        """The robot (uid 1000 in its container) writes its run dir and reads its key; as root we
        hand it its two folders (the CA's key stays root's)."""
        if os.geteuid() != 0:
            return
        for i in self.spec.ids:
            for top in (self.out / "robots" / str(i), self.out / "data" / f"robot{i}"):
                for p in [top, *top.rglob("*")]:
                    os.chown(p, ROBOT_UID, ROBOT_UID, follow_symlinks=False)

    # --- robots ------------------------------------------------------------------------------
    def name(self, robot: int) -> str:
        return self.containers[f"robot{robot}"]

    def start_argv(self, robot: int) -> list[str]:
        """The process that stands for the robot: its container, attached."""
        return ["podman", "start", "--attach", self.name(robot)]

    def after_start(self, robot: int, proc: subprocess.Popen) -> None:
        """Once the container runs: its link service (if any), and what the runner had applied to
        its links (a new start is a new network namespace)."""
        if self._pid(robot, proc) is None:
            return  # it stopped at once: the runner sees the exit and its log
        sidecar = f"robot{robot}-links"
        if sidecar in self.sidecars:
            p = podman("start", "--attach", self.containers[sidecar], check=False, timeout=60)
            with (self.out / "logs" / f"{sidecar}.log").open("a") as log:
                log.write(p.stdout + p.stderr)
            if p.returncode != 0:
                raise PodmanError(f"{sidecar} (tc in robot {robot}'s namespace) failed: {_last_error(p.stderr or p.stdout)}")
        for (a, b), state in self.link_state.items():
            if robot not in (a, b):
                continue
            if not state["up"]:
                self._link_updown(a, b, False, only=robot)
            if state["impair"]:
                self._qdisc(a, b, state["impair"], only=robot)

    def _pid(self, robot: int, proc: subprocess.Popen | None = None, wait_s: float = 60.0) -> int | None:
        """The pid of the container's first process once it runs (None if it stopped first)."""
        deadline = time.monotonic() + wait_s
        while True:
            p = podman("inspect", "--format", "{{.State.Running}} {{.State.Pid}}", self.name(robot), check=False)
            running, _, pid = p.stdout.strip().partition(" ")
            if running == "true" and pid.isdigit() and int(pid) > 0:
                return int(pid)
            if (proc is not None and proc.poll() is not None) or time.monotonic() > deadline:
                return None
            time.sleep(0.1)

    def health_check(self, robot: int) -> subprocess.Popen:
        """The image's HEALTHCHECK, started now (``podman healthcheck run``; exit 0 = healthy)."""
        return subprocess.Popen(["podman", "healthcheck", "run", self.name(robot)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)

    def signal(self, robot: int, sig: int) -> None:
        """A signal to the robot's container: KILL/TERM as such, STOP/CONT as pause/unpause."""
        name = self.name(robot)
        if sig == signal.SIGSTOP:
            podman("pause", name, check=False)
        elif sig == signal.SIGCONT:
            podman("unpause", name, check=False)
        else:
            podman("kill", "--signal", signal.Signals(sig).name.removeprefix("SIG"), name, check=False)

    # --- links -------------------------------------------------------------------------------
    def _key(self, a: int, b: int) -> tuple[int, int]:
        key = (min(a, b), max(a, b))
        if key not in self.link_state:
            raise PodmanError(f"no link {a}-{b} in this topology")
        return key

    def _in_netns(self, robot: int, argv: list[str]) -> subprocess.CompletedProcess:
        pid = self._pid(robot, wait_s=0)
        if pid is None:
            return subprocess.CompletedProcess(argv, 0, "", "")  # not running: applied at its next start
        try:
            p = subprocess.run(["nsenter", "--target", str(pid), "--net", *argv], capture_output=True, text=True,
                               timeout=20)
        except FileNotFoundError as e:
            raise PodmanError(f"{e.filename}: command not found (util-linux's nsenter, iproute2's ip and tc)") from None
        if argv[0] == "tc" or "set" in argv:  # what changed a link, for the operator
            with (self.out / "logs" / "links.log").open("a") as log:
                said = " ".join((p.stderr or p.stdout).split())
                log.write(f"{time.strftime('%H:%M:%S')} robot {robot}: {' '.join(argv)}: "
                          f"{'ok' if p.returncode == 0 else 'failed'}{': ' + said if said else ''}\n")
        return p

    def _device(self, robot: int, other: int) -> str | None:
        """The interface of ``robot``'s container on its link to ``other`` (by its address there)."""
        from cli.scenario.compose import link_addresses

        addr = link_addresses(self.spec.links)[self._key(robot, other)][robot]
        p = self._in_netns(robot, ["ip", "-o", "-4", "addr", "show", "to", f"{addr}/32"])
        return p.stdout.split()[1] if p.stdout.split()[1:] else None

    def _link_updown(self, a: int, b: int, up: bool, only: int | None = None) -> None:
        for robot, other in ((a, b), (b, a)):
            if only not in (None, robot) or (dev := self._device(robot, other)) is None:
                continue
            p = self._in_netns(robot, ["ip", "link", "set", "dev", dev, "up" if up else "down"])
            if p.returncode != 0:
                raise PodmanError(f"link {a}-{b} {'up' if up else 'down'} in robot {robot}: {p.stderr.strip()}")

    def set_link(self, a: int, b: int, up: bool) -> None:
        """Cut (``up=False``) or heal a link: ``ip link set down/up`` on both containers' ends."""
        key = self._key(a, b)
        self._link_updown(*key, up)
        self.link_state[key]["up"] = up

    def _qdisc(self, a: int, b: int, impair: dict | None, only: int | None = None) -> None:
        from cli.scenario.compose import qdisc_variants

        for robot, other in ((a, b), (b, a)):
            if only not in (None, robot) or (dev := self._device(robot, other)) is None:
                continue
            if impair is None:
                self._in_netns(robot, ["tc", "qdisc", "del", "dev", dev, "root"])
                continue
            errors = []
            for qdisc in qdisc_variants(**impair):
                p = self._in_netns(robot, ["tc", "qdisc", "replace", "dev", dev, "root", *qdisc])
                if p.returncode == 0:
                    break
                errors.append(f"{qdisc[0]}: {p.stderr.strip()}")
            else:
                raise PodmanError(f"tc on link {a}-{b} in robot {robot} failed ({'; '.join(errors)}); delay and loss "
                                  "need the kernel's sch_netem (or --mode netns, whose relay emulates them)")

    def impair(self, a: int, b: int, delay_ms: float = 0.0, jitter_ms: float = 0.0, loss: float = 0.0,
               rate_mbit: float = 0.0) -> None:
        """Delay/jitter/loss and a rate cap on link a-b in both directions; all zero: clean again."""
        key = self._key(a, b)
        if self._static(key):
            return  # the compose file's robot<i>-links services set it, at every start of the robots
        clean = not (delay_ms or jitter_ms or loss or rate_mbit)
        impair = None if clean else {"delay_ms": delay_ms, "jitter_ms": jitter_ms, "loss": loss, "rate_mbit": rate_mbit}
        self._qdisc(*key, impair)
        self.link_state[key]["impair"] = impair

    def how(self, fault: str, link: tuple[int, int] | None = None) -> str:
        """How a fault of the timeline reaches the containers (for run.json and the report)."""
        if fault == "netem" and link is not None and self._static(link):
            return f"compose: services robot{link[0]}-links, robot{link[1]}-links (tc at start)"
        return {
            "kill": "runner: podman kill (SIGKILL)",
            "restart": "runner: podman start (same container and run dir)",
            "freeze": "runner: podman pause",
            "thaw": "runner: podman unpause",
            "cut": "runner: ip link set down in both containers' namespaces",
            "heal": "runner: ip link set up in both containers' namespaces",
            "netem": "runner: tc qdisc in both containers' namespaces",
            "netem-end": "runner: tc qdisc del in both containers' namespaces",
        }.get(fault, "runner")

    def _static(self, link: tuple[int, int]) -> bool:
        from cli.scenario.compose import static_impairments

        return any((min(f.link), max(f.link)) == (min(link), max(link)) for f in static_impairments(self.spec))

    # --- teardown ----------------------------------------------------------------------------
    def cleanup(self) -> None:
        """Remove the containers, the pod and the networks of this run (idempotent)."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(PodmanError, OSError):
            self._compose("down", "-t", "5", timeout=180)
        # what podman-compose may have left (a failed `up`): by the project's label
        label = f"label=io.podman.compose.project={self.project}"
        for ident in podman("ps", "-aq", "--filter", label, check=False).stdout.split():
            podman("rm", "-f", ident, check=False)
        for ident in podman("network", "ls", "-q", "--filter", label, check=False).stdout.split():
            podman("network", "rm", "-f", ident, check=False)
        podman("pod", "rm", "-f", f"pod_{self.project}", check=False)
        with contextlib.suppress(Exception):
            atexit.unregister(self.cleanup)

    def describe(self) -> dict:
        from cli.scenario.compose import link_addresses

        return {
            "project": self.project,
            "compose_file": str(self.compose_file),
            "containers": self.containers,
            "links": {f"{a}-{b}": {"network": f"{self.project}_link-{a}-{b}", "subnet": info["subnet"],
                                   "addr": {a: info[a], b: info[b]}}
                      for (a, b), info in link_addresses(self.spec.links).items()},
            "link_services": sorted(self.sidecars),
        }
