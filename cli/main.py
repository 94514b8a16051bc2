"""The ``dinerf-agent`` command line: one typer app, commands registered by the ``cli.cmd_*`` modules."""

from __future__ import annotations

import importlib
from importlib import metadata

import typer

app = typer.Typer(
    name="dinerf-agent",
    help="Peer-to-peer multi-robot NeRF (Di-NeRF) over Zenoh.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Each module adds its commands to ``app`` on import. Keep this list the single place that names them.
COMMAND_MODULES = [
    "cli.cmd_init",
    "cli.cmd_data",
    "cli.cmd_train",
    "cli.cmd_up",
    "cli.cmd_status",
    "cli.cmd_scenario",
    "cli.cmd_outputs",
    "cli.cmd_config",
    "cli.cmd_health",
    "cli.cmd_view",
    "cli.cmd_cert",
]


def _version(value: bool) -> None:
    if value:
        try:
            version = metadata.version("dinerf")
        except metadata.PackageNotFoundError:
            version = "unknown (not installed)"
        typer.echo(f"dinerf-agent {version}")
        raise typer.Exit()


@app.callback()
def _global_options(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log lines (repeatable; debug)."),
    quiet: int = typer.Option(0, "--quiet", "-q", count=True, help="Fewer log lines (warnings only, then errors)."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Peer-to-peer multi-robot NeRF (Di-NeRF) over Zenoh. Log level also from DINERF_LOG=debug|info|warning|error."""
    from cli.logs import configure

    try:
        configure(verbose, quiet)
    except ValueError as e:
        typer.secho(f"error: {e}", err=True, fg=typer.colors.RED)
        raise typer.Exit(2) from None


def _register() -> None:
    for name in COMMAND_MODULES:
        importlib.import_module(name)


def main() -> None:
    _register()
    app()

