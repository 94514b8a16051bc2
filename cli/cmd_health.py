"""``dinerf-agent health RUN_DIR``: is this robot making progress? (a container's healthcheck)."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from cli.errors import friendly_errors
from cli.main import app


def run_dir_health(run_dir: Path, max_age_s: float, now: float | None = None) -> tuple[bool, str]:
    """Healthy when the robot has finished, or wrote a round, an event or a checkpoint within ``max_age_s``."""
    from agent.checkpoint import RunFolder

    if not run_dir.is_dir():
        return False, f"{run_dir}: no such run folder (the daemon has not started)"
    folder = RunFolder(run_dir, create=False)
    if folder.done.is_file():
        return True, f"{run_dir}: done"
    written = [p.stat().st_mtime for p in (folder.telemetry, folder.events, folder.checkpoint) if p.is_file()]
    if not written:
        return False, f"{run_dir}: nothing written yet"
    age = (time.time() if now is None else now) - max(written)
    if age > max_age_s:
        return False, f"{run_dir}: no round, event or checkpoint for {age:.0f} s (more than {max_age_s:.0f} s)"
    return True, f"{run_dir}: last wrote {age:.0f} s ago"


@app.command()
@friendly_errors
def health(
    run_dir: Path = typer.Argument(..., help="The robot's --run-dir."),
    max_age: float = typer.Option(600.0, help="Unhealthy after this many seconds without a round, event or checkpoint."),
) -> None:
    """Exit 0 if the robot in RUN_DIR is done or progressing, 1 if not (Docker HEALTHCHECK)."""
    ok, why = run_dir_health(run_dir, max_age)
    typer.echo(why)
    if not ok:
        raise typer.Exit(1)
