"""``dinerf-agent scenario ...``: run named swarm experiments, report on them, export them to compose."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app
from cli.options import progress_listener

scenario_app = typer.Typer(help="Named swarm experiments: run (loopback, network namespaces or containers), report, compose.",
                           no_args_is_help=True)
app.add_typer(scenario_app, name="scenario")

SCENARIO_HELP = "A scenario name (a folder of scenarios/) or a path to a scenario folder or scenario.toml."


def _load(name: str, overrides: list[str]):
    from cli.config import apply_overrides, merge_tables, overrides_table
    from cli.scenario.spec import find_scenario, load_scenario

    spec = load_scenario(find_scenario(name))
    if overrides:
        path, given = spec.path, spec.given_train
        spec = apply_overrides(spec, overrides)
        spec.path = path
        spec.given_train = merge_tables(given, overrides_table(overrides).get("training", {}).get("train", {}))
    return spec


@scenario_app.command("list")
@friendly_errors
def list_cmd() -> None:
    """Show the scenarios shipped in scenarios/."""
    from rich.console import Console
    from rich.table import Table

    from cli.config import ConfigError
    from cli.scenario.spec import list_scenarios, load_scenario

    table = Table(title="scenarios (dinerf-agent scenario run NAME)")
    table.add_column("name", no_wrap=True)
    for col in ("robots", "topology", "data", "rounds x steps", "faults", "mode"):
        table.add_column(col)
    for folder in list_scenarios():
        try:
            s = load_scenario(folder)
        except (ConfigError, ValueError) as e:
            table.add_row(folder.name, "", "", f"[red]invalid: {e}[/red]", "", "", "")
            continue
        f = s.faults
        faults = ", ".join(f"{n} {kind}" for kind, n in f.counts().items()) or "-"
        data = s.dataset.split(":")[0] if s.dataset.startswith("procedural") else Path(s.dataset).name
        table.add_row(s.name, str(s.robots), s.topology.kind, data, f"{s.training.rounds} x {s.training.steps_per_round}",
                      faults, s.run.mode)
    Console().print(table)


@scenario_app.command("run")
@friendly_errors
def run_cmd(
    name: str = typer.Argument(..., help=SCENARIO_HELP),
    mode: str = typer.Option(None, "--mode", help="local (loopback, any user) | netns (root: a namespace per robot) | "
                             "compose (root: a podman container per robot, from the scenario's compose file). Default: the scenario's."),
    out: Path = typer.Option(None, "--out", help="Output folder (default: runs/scenarios/<name>/<time>)."),
    overrides: list[str] = typer.Option([], "--set", help="Override a scenario setting, e.g. --set training.rounds=4 (repeatable)."),
    report: bool = typer.Option(True, "--report/--no-report", help="Evaluate the run and write report.md/json + PNGs."),
    force: bool = typer.Option(False, "--force", help="Replace the output of an earlier run in --out (a folder holding run.json)."),
) -> None:
    """Run a scenario: split the data, start one daemon per robot, apply the faults, write the report."""
    from cli.options import check_output_folder
    from cli.scenario.netns import NetnsError, netns_unavailable_reason
    from cli.scenario.podman import PodmanError, compose_unavailable_reason
    from cli.scenario.report import build_report
    from cli.scenario.runner import ScenarioRunner

    spec = _load(name, overrides)
    mode = mode or spec.run.mode
    spec.check_mode(mode)
    if mode == "netns" and (reason := netns_unavailable_reason()):
        raise UserError(f"--mode netns: {reason}")
    if mode == "compose" and (reason := compose_unavailable_reason()):
        raise UserError(f"--mode compose: {reason}")
    if spec.needs_files():
        spec.resolved_dataset()  # a missing dataset is an error now, not after the set-up
    out = out or Path("runs") / "scenarios" / spec.name / time.strftime("%Y%m%d-%H%M%S")
    check_output_folder(out, "--out")
    if out.exists() and any(out.iterdir()):
        if not (force and (out / "run.json").is_file()):
            raise UserError(f"--out {out}: folder is not empty; choose another"
                            + (" (--force replaces only an earlier scenario run's folder)" if force else
                               " or pass --force to replace an earlier run"))
        import shutil

        shutil.rmtree(out)
    typer.echo(f"[scenario] {spec.name} ({mode}) -> {out}")
    try:
        if mode == "compose":  # the image of this checkout (from the layer cache when nothing changed)
            from cli.scenario.compose import IMAGE
            from cli.scenario.images import build_image

            (out / "logs").mkdir(parents=True, exist_ok=True)
            build_image(IMAGE, log=out / "logs" / "image.log", echo=typer.echo)
        outcome = ScenarioRunner(spec, out, mode=mode, echo=typer.echo).run()
    except NetnsError as e:  # the namespaces are already gone: the runner cleans up before re-raising
        raise UserError(f"network set-up failed: {e}") from None
    except PodmanError as e:  # so are the containers and their networks
        raise UserError(f"--mode compose: {e}") from None
    typer.echo(f"[scenario] {'completed' if outcome.ok else 'FAILED'}: {outcome.reason} ({outcome.seconds:.0f} s)")
    if report and (out / "data" / "truth.json").is_file():
        with progress_listener():
            build_report(out, echo=typer.echo)
    if not outcome.ok:
        raise typer.Exit(1)


@scenario_app.command("report")
@friendly_errors
def report_cmd(out: Path = typer.Argument(..., help="The output folder of a `scenario run`.")) -> None:
    """(Re)build the report of a run folder."""
    from cli.scenario.report import build_report

    if not (out / "run.json").is_file():
        raise UserError(f"{out}: no run.json (not the output folder of `dinerf-agent scenario run`)")
    with progress_listener():
        build_report(out, echo=typer.echo)


@scenario_app.command("compare")
@friendly_errors
def compare_cmd(
    runs: list[Path] = typer.Argument(..., help="Output folders of fault scenario runs."),
    fault_free: Path = typer.Option(..., "--fault-free", help="The output folder of the same swarm run without faults."),
    tolerance_db: float = typer.Option(0.5, "--tolerance-db", help="How far below the fault-free PSNR a robot may end."),
    json_out: Path = typer.Option(None, "--json", help="Also write the comparisons to this JSON file."),
) -> None:
    """Compare fault runs with the fault-free run: PSNR per robot, rounds finished, rounds lost at restarts."""
    import json

    from cli.scenario.compare import CompareError, compare_runs, format_comparison

    try:
        comparisons = [compare_runs(run, fault_free, tolerance_db) for run in runs]
    except CompareError as e:
        raise UserError(str(e)) from None
    typer.echo("\n\n".join(format_comparison(c) for c in comparisons))
    if json_out is not None:
        json_out.write_text(json.dumps([c.to_json() for c in comparisons], indent=2) + "\n")
    if not all(c.ok for c in comparisons):
        raise typer.Exit(1)


@scenario_app.command("compose")
@friendly_errors
def compose_cmd(
    name: str = typer.Argument(..., help=SCENARIO_HELP),
    out: Path = typer.Option(None, "--out", help="The compose file to write (default: scenarios/<name>/docker-compose.yml)."),
    data: bool = typer.Option(False, "--data/--no-data", help="Also write the robot folders (the split) beside it, in data/."),
) -> None:
    """Write a docker-compose.yml: one service per robot, one network per link (and the swarm TOML it mounts)."""
    from cli.scenario.compose import write_compose

    spec = _load(name, [])
    path = write_compose(spec, out or spec.path.parent / "docker-compose.yml", with_data=data)
    typer.echo(f"wrote {path} and {path.parent / 'swarm.toml'}"
               + ("" if data else f"; write the robot folders with --data (into {path.parent / 'data'})"))


@scenario_app.command("image")
@friendly_errors
def image_cmd(
    base: str = typer.Option("auto", "--base", help="The base image: a registry's (python:3.11-slim), `debootstrap` "
                             "(a Debian base made here once, for machines that reach no registry), or auto: the "
                             "registry's if it is here, else debootstrap; or the previous build's."),
    torch_spec: str = typer.Option(None, "--torch-spec", help="What pip installs as torch (default torch==2.13.0)."),
    torch_index: str = typer.Option(None, "--torch-index", help="The index for torch; '' for pip's configuration "
                                    "(default: the CPU index, or '' when the host's pip has a torch wheel at hand)."),
    mirror: str = typer.Option("http://deb.debian.org/debian", "--mirror", help="The Debian mirror of debootstrap."),
) -> None:
    """Build the robot image (dinerf-agent:latest) with podman, for `scenario run --mode compose`."""
    import shutil

    from cli.scenario.compose import IMAGE
    from cli.scenario.images import build_image
    from cli.scenario.podman import PodmanError

    if shutil.which("podman") is None:
        raise UserError("podman is not installed (Debian: apt-get install podman)")
    try:
        build_image(IMAGE, base, torch_spec, torch_index, echo=typer.echo, mirror=mirror)
    except PodmanError as e:
        raise UserError(str(e)) from None


@scenario_app.command("cleanup")
@friendly_errors
def cleanup_cmd(
    prefix: str = typer.Option("dinerf", help="Namespace prefix of scenario runs."),
    force: bool = typer.Option(False, help="Also remove namespaces and containers of runs whose process is still alive."),
) -> None:
    """Remove network namespaces and compose containers left by crashed scenario runs (root)."""
    import os
    import shutil

    from cli.scenario.netns import cleanup_stale, netns_unavailable_reason
    from cli.scenario.podman import cleanup_stale_projects

    if reason := netns_unavailable_reason():
        raise UserError(reason)
    removed = cleanup_stale(prefix, force=force)
    typer.echo(f"removed {len(removed)} namespace(s)" + (": " + ", ".join(removed) if removed else ""))
    if shutil.which("podman") and os.geteuid() == 0:
        projects = cleanup_stale_projects(force=force)
        typer.echo(f"removed {len(projects)} compose run(s)" + (": " + ", ".join(projects) if projects else ""))
