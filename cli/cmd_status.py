"""``dinerf-agent status``: watch a swarm live, from the status messages robots publish."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import typer
from rich.console import Console
from rich.live import Live
from rich.table import Table

from agent.telemetry import coverage_text
from cli.errors import UserError, friendly_errors
from cli.main import app


def status_table(latest: dict, now: float, swarm_name: str) -> Table:
    """One row per robot from its newest Status (``latest``: id -> (Status, received monotonic))."""
    table = Table(title=f"swarm {swarm_name} — {len(latest)} robot(s) heard")
    for col in ("robot", "round", "phase", "loss", "psnr", "pose est. (deg, |t|, s)", "frame", "heard", "in MB",
                "out MB", "rejected", "distrusts", "ref", "alive", "keyframes", "seen"):
        table.add_column(col, justify="right" if col not in ("phase", "frame", "heard", "distrusts", "alive") else "left")
    for rid in sorted(latest):
        msg, seen = latest[rid]
        log_s, phi, t = msg.pose[0], msg.pose[1:4], msg.pose[4:7]
        rot = math.degrees(math.sqrt(sum(x * x for x in phi)))
        table.add_row(
            str(rid), str(msg.round), msg.phase,
            "-" if msg.loss is None else f"{msg.loss:.4f}",
            "-" if msg.psnr is None else f"{msg.psnr:.2f}",
            f"{rot:.2f}, {math.sqrt(sum(x * x for x in t)):.3f}, {math.exp(log_s):.3f}",
            _frame_state(msg),
            ",".join(map(str, msg.neighbours_heard)) or "-",
            f"{msg.bytes_in / 1e6:.1f}", f"{msg.bytes_out / 1e6:.1f}",
            str(sum(msg.rejected.values())), _suspects(msg), str(msg.reference),
            ",".join(map(str, sorted(msg.alive_ages))) or "-",
            _views(msg),
            f"{now - seen:.1f} s ago",
        )
    return table


def status_json(latest: dict, now: float, swarm_name: str) -> str:
    """The same rows as :func:`status_table`, as JSON for scripts (pose: log-scale, rotation vector, t)."""
    import json

    robots = []
    for rid in sorted(latest):
        msg, seen = latest[rid]
        robots.append({
            "robot": rid, "round": msg.round, "phase": msg.phase, "loss": msg.loss, "psnr": msg.psnr,
            "pose": list(msg.pose), "alignment": msg.alignment.value, "alignment_detail": msg.alignment_detail,
            "heard": list(msg.neighbours_heard), "bytes_in": msg.bytes_in, "bytes_out": msg.bytes_out,
            "rejected": dict(msg.rejected), "suspects": {str(j): why for j, why in sorted(msg.suspects.items())},
            "reference": msg.reference, "alive": sorted(msg.alive_ages), "views": msg.views,
            "seen_s_ago": round(now - seen, 3),
        })
    return json.dumps({"swarm": swarm_name, "robots": robots}, indent=2)


def _views(msg) -> str:
    """A robot whose views arrive while it trains: keyframes (held out, dropped), the newest's age, the area."""
    v = msg.views
    if v is None:
        return "-"
    age = "-" if v["newest_age_s"] is None else f"{v['newest_age_s']:.1f} s"
    return (f"{v['keyframes']} (+{v['held_out']} held, {v['dropped']} dropped), newest {age}, "
            f"area {coverage_text(v['coverage'])}")


def _suspects(msg) -> str:
    """The neighbours this robot does not trust and why (clipped, quarantined, ahead_of_pace, refused)."""
    return ", ".join(f"[red]{j}: {why}[/red]" for j, why in sorted(msg.suspects.items())) or "-"


def _frame_state(msg) -> str:
    """How the robot's frame is placed; an unaligned robot is out of consensus, and says so."""
    state = msg.alignment.value
    if state == "unaligned":
        return "[red]UNALIGNED (alone)[/red]"
    return state + (f": {msg.alignment_detail}" if msg.alignment_detail else "")


@app.command()
@friendly_errors
def status(
    swarm: Path = typer.Option(..., "--swarm", help="The swarm TOML (its endpoints tell where to connect)."),
    connect: list[str] = typer.Option([], "--connect", help="Extra Zenoh endpoint to connect to (repeatable)."),
    once: float = typer.Option(0.0, help="Print one table after this many seconds and exit (0 = live view)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON once (after --once seconds, default 3) and exit."),
) -> None:
    """Show every robot's round, loss, PSNR, pose, traffic and rejections, live."""
    from cli.swarm_file import load_swarm_file
    from protocol import codec
    from protocol.keys import Keys
    from protocol.messages import Rejected
    from protocol.transport import TransportError, ZenohTransport

    cfg, base_dir = load_swarm_file(swarm)
    endpoints = list(connect) or [e for i in cfg.swarm.robots if (e := cfg.endpoint(i))]
    if not endpoints and not cfg.network.multicast_scouting:
        raise UserError("no endpoints in the swarm file and none given with --connect")
    keys = Keys(cfg.swarm.name)
    expect = codec.Expectation(cfg.swarm.name, allowed_senders=frozenset(cfg.swarm.robots))
    latest: dict = {}
    lock = threading.Lock()

    def on_status(key: str, data: bytes) -> None:
        try:
            msg = codec.decode(data, expect, kind="status", key=keys.parse(key))
        except (Rejected, ValueError):
            return
        with lock:
            latest[msg.sender] = (msg, time.monotonic())

    tcfg = cfg.monitor_transport(base_dir, endpoints)  # the monitor certificate of a secure swarm
    observer_id = max(cfg.swarm.robots) + 1000  # never declared alive: it only listens
    try:
        net = ZenohTransport(tcfg, keys, observer_id).open()
    except TransportError as e:
        raise UserError(f"cannot open the Zenoh session: {e}") from None
    console = Console()
    try:
        net.subscribe(keys.status_all(), on_status)
        if once > 0 or as_json:
            time.sleep(once if once > 0 else 3.0)
            with lock:
                snapshot = dict(latest)
            if as_json:
                print(status_json(snapshot, time.monotonic(), cfg.swarm.name), flush=True)
            else:
                console.print(status_table(snapshot, time.monotonic(), cfg.swarm.name))
            return
        with Live(console=console, refresh_per_second=2) as live:
            while True:
                with lock:
                    live.update(status_table(dict(latest), time.monotonic(), cfg.swarm.name))
                time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        net.close()
