"""An emulated mesh network: one network namespace per robot, one veth pair per topology link.

Why namespaces: a robot in its own namespace can only reach the robots it shares a link with,
so the topology is enforced by the network (not by configuration), and a link can really be
cut (``ip link set down``) or made slow and lossy.

Layout of one run (``lab = NetnsLab([1, 2, 3], [(1, 2), (2, 3)]); lab.create()``):

- namespace ``<run>-r<id>`` per robot, ``<run> = <prefix>-<pid>-<4 hex>`` so parallel runs never
  clash and :func:`cleanup_stale` can tell a crashed run's leftovers (owner pid gone) from a
  live one;
- link e (the e-th sorted edge a < b) is a /30 of ``198.18.0.0/15`` (RFC 2544's benchmarking
  range, never routed): ``a`` gets ``.1``, ``b`` gets ``.2``; the interface in robot a's
  namespace is ``v<b>`` and vice versa. A robot listens on each of its link addresses and
  connects to its neighbours' addresses on the shared links (:meth:`NetnsLab.endpoints`);
- veths are created directly inside the namespaces, so deleting the namespaces removes them:
  nothing is ever left in the root namespace.

Impairment (delay/jitter/loss, a rate cap) uses ``tc qdisc ... netem`` on both ends of the link when the
kernel has ``sch_netem``; otherwise (``impair="relay"``, or ``"auto"`` on such a kernel) an
impairable link is built through a relay namespace ``<run>-l<a>-<b>`` in which
:mod:`cli.scenario.linkemu` forwards frames with the delay and loss. Which links may be impaired
must be known at creation (``impairable=``): the runner reads it from the fault timeline.

Cleanup: every lab registers itself; :meth:`NetnsLab.cleanup` (idempotent) stops the relays
and deletes every namespace it made. It runs from ``with NetnsLab(...)``, from ``atexit``, and
on SIGINT/SIGTERM when :func:`signals_raise` is in effect (it turns SIGTERM into
``KeyboardInterrupt`` so ``finally`` blocks run).
"""

from __future__ import annotations

import atexit
import contextlib
import ipaddress
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Literal

DEFAULT_PREFIX = "dinerf"
DEFAULT_BASE = "198.18.0.0/15"
ZENOH_PORT = 7447

__all__ = [
    "NetnsError",
    "NetnsLab",
    "Link",
    "netns_unavailable_reason",
    "netem_available",
    "cleanup_stale",
    "list_namespaces",
    "signals_raise",
    "run_ip",
    "netem_args",
]


class NetnsError(RuntimeError):
    """A namespace/link command failed (the message holds the command and its stderr)."""


def run_ip(*args: str, ns: str | None = None, check: bool = True, timeout: float = 20.0) -> subprocess.CompletedProcess:
    """Run ``ip ARGS`` (or, with ``ns``, ``ip -n NS ARGS``)."""
    argv = ["ip"] + (["-n", ns] if ns else []) + list(args)
    return _run(argv, check, timeout)


def _run(argv: list[str], check: bool = True, timeout: float = 20.0) -> subprocess.CompletedProcess:
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    except FileNotFoundError:
        raise NetnsError(f"{argv[0]}: command not found (install iproute2)") from None
    except subprocess.TimeoutExpired:
        raise NetnsError(f"{' '.join(argv)}: timed out after {timeout} s") from None
    if check and p.returncode != 0:
        raise NetnsError(f"{' '.join(argv)} failed: {p.stderr.strip() or p.stdout.strip()}")
    return p


def netns_unavailable_reason() -> str | None:
    """None when namespaces can be made here, else why not (for a one-line error or a test skip)."""
    if sys.platform != "linux":
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root (run as root, or use --mode local)"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    name = f"{DEFAULT_PREFIX}probe-{os.getpid()}-{secrets.token_hex(2)}"
    try:
        run_ip("netns", "add", name)
    except NetnsError as e:
        return f"cannot create a network namespace: {e}"
    run_ip("netns", "del", name, check=False)
    return None


_NETEM: bool | None = None


def netem_available() -> bool:
    """Whether ``tc qdisc add ... netem`` works on this kernel (probed once, in a scratch namespace)."""
    global _NETEM
    if _NETEM is None:
        if shutil.which("tc") is None or netns_unavailable_reason() is not None:
            _NETEM = False
            return _NETEM
        name = f"{DEFAULT_PREFIX}probe-{os.getpid()}-{secrets.token_hex(2)}"
        try:
            run_ip("netns", "add", name)
            run_ip("link", "add", "p0", "type", "veth", "peer", "name", "p1", ns=name)
            p = _run(["ip", "netns", "exec", name, "tc", "qdisc", "add", "dev", "p0", "root", "netem", "delay", "1ms"],
                     check=False)
            _NETEM = p.returncode == 0
        except NetnsError:
            _NETEM = False
        finally:
            run_ip("netns", "del", name, check=False)
    return _NETEM


def netem_args(delay_ms: float, jitter_ms: float = 0.0, loss: float = 0.0, rate_mbit: float = 0.0) -> list[str]:
    """``tc qdisc ... netem`` arguments (with a rate: netem's own, the delay after the wire)."""
    args = ["delay", f"{delay_ms}ms"] + ([f"{jitter_ms}ms"] if jitter_ms else []) + (["loss", f"{100 * loss}%"] if loss else [])
    return args + (["rate", f"{rate_mbit}mbit"] if rate_mbit else [])


def list_namespaces() -> list[str]:
    p = run_ip("netns", "list", check=False)
    return [line.split()[0] for line in p.stdout.splitlines() if line.strip()]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _owner_pid(ns: str, prefix: str) -> int | None:
    """``<prefix>-<pid>-<hex>-...`` -> pid (None if the name does not follow the pattern)."""
    rest = ns[len(prefix) + 1:] if ns.startswith(prefix + "-") else ""
    head = rest.split("-", 1)[0]
    return int(head) if head.isdigit() else None


def _ns_pids(ns: str) -> list[int]:
    p = run_ip("netns", "pids", ns, check=False)
    return [int(x) for x in p.stdout.split() if x.isdigit()]


def _delete_namespace(ns: str) -> None:
    """Kill what still runs inside (only processes in that namespace), then delete it."""
    for pid in _ns_pids(ns):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    run_ip("netns", "del", ns, check=False)


def cleanup_stale(prefix: str = DEFAULT_PREFIX, force: bool = False) -> list[str]:
    """Delete namespaces ``<prefix>-<pid>-...`` whose owner process is gone (all of them with ``force``).

    Returns the names removed. A live run (owner alive) is left alone unless ``force``.
    """
    removed = []
    for ns in list_namespaces():
        if not ns.startswith(prefix + "-"):
            continue
        pid = _owner_pid(ns, prefix)
        if not force and pid is not None and pid != os.getpid() and _pid_alive(pid):
            continue
        if not force and pid == os.getpid() and any(ns.startswith(lab.run_id + "-") for lab in list(_LABS)):
            continue  # ours and still in use
        _delete_namespace(ns)
        removed.append(ns)
    return removed


@dataclass
class Link:
    a: int  # lower id
    b: int
    index: int
    net: ipaddress.IPv4Network
    relay_ns: str | None = None  # set when the link goes through a linkemu relay

    @property
    def addr_a(self) -> str:
        return str(self.net.network_address + 1)

    @property
    def addr_b(self) -> str:
        return str(self.net.network_address + 2)

    def addr(self, robot: int) -> str:
        return self.addr_a if robot == self.a else self.addr_b

    def other(self, robot: int) -> int:
        return self.b if robot == self.a else self.a

    @staticmethod
    def ifname(peer: int) -> str:
        """The interface in a robot's namespace that leads to ``peer``."""
        return f"v{peer}"


_LABS: list["NetnsLab"] = []
_LOCK = threading.Lock()


def _cleanup_all() -> None:
    for lab in list(_LABS):
        lab.cleanup()


atexit.register(_cleanup_all)


class NetnsLab:
    """The namespaces and links of one run (see the module docstring)."""

    def __init__(
        self,
        ids: Iterable[int],
        links: Iterable[tuple[int, int]],
        prefix: str = DEFAULT_PREFIX,
        base: str = DEFAULT_BASE,
        impairable: Iterable[tuple[int, int]] = (),
        impair: Literal["auto", "netem", "relay"] = "auto",
        log_dir: Path | None = None,
    ) -> None:
        self.ids = sorted(ids)
        self.prefix = prefix
        self.run_id = f"{prefix}-{os.getpid()}-{secrets.token_hex(2)}"
        net = ipaddress.ip_network(base)
        subnets = net.subnets(new_prefix=30)
        self.links: dict[tuple[int, int], Link] = {}
        for i, (a, b) in enumerate(sorted({(min(x, y), max(x, y)) for x, y in links})):
            for r in (a, b):
                if r not in self.ids:
                    raise NetnsError(f"link {a}-{b}: robot {r} is not one of {self.ids}")
            try:
                sub = next(subnets)
            except StopIteration:
                raise NetnsError(f"{base} has no room for {i + 1} links") from None
            self.links[(a, b)] = Link(a, b, i, sub)
        self.impairable = {(min(a, b), max(a, b)) for a, b in impairable}
        for key in self.impairable:
            if key not in self.links:
                raise NetnsError(f"link {key[0]}-{key[1]} to impair is not a link of the topology")
        if impair not in ("auto", "netem", "relay"):
            raise NetnsError(f"impair must be auto, netem or relay, got {impair!r}")
        self.impair_mode = impair
        self.log_dir = log_dir
        self.namespaces: list[str] = []  # everything made, in order (deleted in reverse)
        self.relays: dict[tuple[int, int], subprocess.Popen] = {}
        self._logs: list = []  # relay log files, closed by cleanup
        self.link_state: dict[tuple[int, int], dict] = {k: {"up": True, "impair": None} for k in self.links}
        self.created = False
        self._closed = False

    # --- names --------------------------------------------------------------------------------
    def ns(self, robot: int) -> str:
        return f"{self.run_id}-r{robot}"

    def link(self, a: int, b: int) -> Link:
        key = (min(a, b), max(a, b))
        if key not in self.links:
            raise NetnsError(f"no link {a}-{b} (links: {', '.join(f'{x}-{y}' for x, y in self.links)})")
        return self.links[key]

    def neighbours(self, robot: int) -> list[int]:
        return sorted(l.other(robot) for l in self.links.values() if robot in (l.a, l.b))

    def endpoints(self, robot: int, port: int = ZENOH_PORT) -> tuple[list[str], list[str]]:
        """(listen, connect) Zenoh endpoints of ``robot``: its link addresses, its neighbours' ones.

        Both ends of a link connect to each other (as with ``[network.endpoints]``: a robot
        connects to every neighbour), so whichever restarts, the other side reaches it again.
        """
        listen, connect = [], []
        for l in sorted(self.links.values(), key=lambda l: l.index):
            if robot not in (l.a, l.b):
                continue
            listen.append(f"tcp/{l.addr(robot)}:{port}")
            connect.append(f"tcp/{l.addr(l.other(robot))}:{port}")
        return listen, connect

    def exec_argv(self, robot: int, argv: list[str]) -> list[str]:
        """``argv`` run inside robot's namespace."""
        return ["ip", "netns", "exec", self.ns(robot)] + list(argv)

    # --- building ----------------------------------------------------------------------------
    def _use_relay(self) -> bool:
        if not self.impairable or self.impair_mode == "netem":
            return False
        return self.impair_mode == "relay" or not netem_available()

    def create(self) -> "NetnsLab":
        """Make the namespaces and links; on any failure, remove what was made and raise."""
        if self.created:
            return self
        reason = netns_unavailable_reason()
        if reason:
            raise NetnsError(reason)
        if self.impair_mode == "netem" and self.impairable and not netem_available():
            raise NetnsError("this kernel has no sch_netem (tc ... netem fails); use impair = \"relay\" or \"auto\"")
        with _LOCK:
            _LABS.append(self)
        try:
            for r in self.ids:
                self._add_ns(self.ns(r))
            relay = self._use_relay()
            for key, l in self.links.items():
                if relay and key in self.impairable:
                    self._relayed_link(l)
                else:
                    self._direct_link(l)
            self.created = True
        except BaseException:
            self.cleanup()
            raise
        return self

    def _add_ns(self, name: str) -> None:
        run_ip("netns", "add", name)
        self.namespaces.append(name)
        run_ip("link", "set", "lo", "up", ns=name)

    def _direct_link(self, l: Link) -> None:
        na, nb = self.ns(l.a), self.ns(l.b)
        ia, ib = Link.ifname(l.b), Link.ifname(l.a)
        run_ip("link", "add", ia, "netns", na, "type", "veth", "peer", "name", ib, "netns", nb)
        self._address(l)

    def _relayed_link(self, l: Link) -> None:
        """a <-> [relay ns: to<a> | linkemu | to<b>] <-> b."""
        relay = f"{self.run_id}-l{l.a}-{l.b}"
        self._add_ns(relay)
        l.relay_ns = relay
        ends = ((l.a, Link.ifname(l.b), f"to{l.a}"), (l.b, Link.ifname(l.a), f"to{l.b}"))
        for robot, ifname, relay_if in ends:
            run_ip("link", "add", ifname, "netns", self.ns(robot), "type", "veth", "peer", "name", relay_if, "netns", relay)
            run_ip("link", "set", ifname, "gso_max_segs", "1", ns=self.ns(robot))
            run_ip("link", "set", relay_if, "gso_max_segs", "1", ns=relay)
            run_ip("link", "set", relay_if, "up", ns=relay)
        self._address(l)
        log = open(self.log_dir / f"relay-{l.a}-{l.b}.log", "w") if self.log_dir else subprocess.DEVNULL  # noqa: SIM115
        if self.log_dir:
            self._logs.append(log)
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        proc = subprocess.Popen(
            ["ip", "netns", "exec", relay, sys.executable, "-u", "-m", "cli.scenario.linkemu", f"to{l.a}", f"to{l.b}"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log, text=True, env=env,
        )
        self.relays[(l.a, l.b)] = proc
        line = proc.stdout.readline().strip() if proc.stdout else ""
        if line != "ready":
            raise NetnsError(f"link emulator for {l.a}-{l.b} did not start (said {line!r}, exit {proc.poll()})")
        # keep its counters in the log from now on (and never let its stdout pipe fill up)
        threading.Thread(target=_copy_lines, args=(proc.stdout, log if self.log_dir else None), daemon=True).start()

    def _address(self, l: Link) -> None:
        for robot in (l.a, l.b):
            ns, ifname = self.ns(robot), Link.ifname(l.other(robot))
            run_ip("addr", "add", f"{l.addr(robot)}/{l.net.prefixlen}", "dev", ifname, ns=ns)
            run_ip("link", "set", ifname, "up", ns=ns)

    # --- faults ------------------------------------------------------------------------------
    def set_link(self, a: int, b: int, up: bool) -> None:
        """Cut (``up=False``) or heal a link: ``ip link set down/up`` on both robot ends."""
        l = self.link(a, b)
        for robot in (l.a, l.b):
            run_ip("link", "set", Link.ifname(l.other(robot)), "up" if up else "down", ns=self.ns(robot))
        self.link_state[(l.a, l.b)]["up"] = up

    def impair(self, a: int, b: int, delay_ms: float = 0.0, jitter_ms: float = 0.0, loss: float = 0.0,
               rate_mbit: float = 0.0) -> None:
        """Delay/jitter/loss and a rate cap (Mbit/s, 0: none) on link a-b in both directions; all
        zero makes it clean again."""
        l = self.link(a, b)
        key = (l.a, l.b)
        clean = delay_ms == 0 and jitter_ms == 0 and loss == 0 and rate_mbit == 0
        if key in self.relays:
            proc = self.relays[key]
            if proc.poll() is not None or proc.stdin is None:
                raise NetnsError(f"link emulator of {a}-{b} is not running (exit {proc.poll()})")
            proc.stdin.write(json.dumps({"delay_ms": delay_ms, "jitter_ms": jitter_ms, "loss": loss,
                                         "rate_mbit": rate_mbit}) + "\n")
            proc.stdin.flush()
        else:
            if key not in self.impairable and not clean and self.impair_mode != "netem" and not netem_available():
                raise NetnsError(f"link {a}-{b} was not declared impairable and this kernel has no netem")
            for robot in (l.a, l.b):
                dev = Link.ifname(l.other(robot))
                tc = ["ip", "netns", "exec", self.ns(robot), "tc", "qdisc"]
                if clean:
                    _run(tc + ["del", "dev", dev, "root"], check=False)
                else:
                    _run(tc + ["replace", "dev", dev, "root", "netem"] + netem_args(delay_ms, jitter_ms, loss, rate_mbit))
        self.link_state[key]["impair"] = None if clean else {"delay_ms": delay_ms, "jitter_ms": jitter_ms, "loss": loss,
                                                             "rate_mbit": rate_mbit}

    def impair_backend(self, a: int, b: int) -> str:
        l = self.link(a, b)
        return "relay" if (l.a, l.b) in self.relays else "netem"

    # --- teardown ----------------------------------------------------------------------------
    def cleanup(self) -> None:
        """Stop the relays and delete every namespace this lab made (and so every veth). Idempotent."""
        if self._closed:
            return
        self._closed = True
        for proc in self.relays.values():
            with contextlib.suppress(Exception):
                if proc.stdin:
                    proc.stdin.close()  # the emulator reports its counters and exits
            with contextlib.suppress(Exception):
                proc.wait(timeout=2)
            with contextlib.suppress(Exception):
                if proc.poll() is None:
                    proc.terminate()
                    proc.wait(timeout=3)
            if proc.poll() is None:
                with contextlib.suppress(Exception):
                    proc.kill()
                    proc.wait(timeout=3)
        for name in reversed(self.namespaces):
            _delete_namespace(name)
        for f in self._logs:
            with contextlib.suppress(Exception):
                f.close()
        with _LOCK:
            if self in _LABS:
                _LABS.remove(self)

    def __enter__(self) -> "NetnsLab":
        return self.create()

    def __exit__(self, *exc) -> None:
        self.cleanup()

    def describe(self) -> dict:
        """For the report: namespaces, addresses, how impairment is done."""
        return {
            "run_id": self.run_id,
            "namespaces": {r: self.ns(r) for r in self.ids},
            "links": {
                f"{l.a}-{l.b}": {"subnet": str(l.net), "addr": {l.a: l.addr_a, l.b: l.addr_b},
                                 "impair": "relay" if l.relay_ns else ("netem" if (l.a, l.b) in self.impairable else None)}
                for l in self.links.values()
            },
        }


def _copy_lines(src, dst) -> None:
    with contextlib.suppress(Exception):
        for line in src:
            if dst is not None:
                dst.write(line)
                dst.flush()


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """Within the block, SIGTERM (and SIGINT, as usual) raise KeyboardInterrupt, so ``finally`` runs.

    Only in the main thread (signal handlers can only be set there); elsewhere a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def raise_interrupt(signum, frame):  # noqa: ARG001
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    old = {s: signal.signal(s, raise_interrupt) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
