"""The ``dinerf-agent`` command line: one typer app, commands registered by the ``cli.cmd_*`` modules."""

from __future__ import annotations

import importlib

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
    "cli.cmd_data",
    "cli.cmd_train",
    "cli.cmd_up",
    "cli.cmd_status",
    "cli.cmd_scenario",
    "cli.cmd_cert",
]


def _register() -> None:
    for name in COMMAND_MODULES:
        importlib.import_module(name)


def main() -> None:
    _register()
    app()

