"""``dinerf-agent config show``: the effective configuration, every default written out."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app

config_app = typer.Typer(help="Inspect configuration.", no_args_is_help=True)
app.add_typer(config_app, name="config")


@config_app.command("show")
@friendly_errors
def show_cmd(
    swarm: Path = typer.Option(None, "--swarm", help="A swarm TOML (as `up` reads it)."),
    scenario: str = typer.Option(None, "--scenario", help="A scenario name or folder (as `scenario run` reads it)."),
    overrides: list[str] = typer.Option([], "--set", help="Apply an override first, e.g. --set training.rounds=5."),
) -> None:
    """Print the configuration a command would run with, as TOML, with every default; an unset key
    (decided at run time, e.g. from the swarm's frames) is a comment."""
    from cli.config import to_dict
    from cli.scenario.tomlout import dumps

    if (swarm is None) == (scenario is None):
        raise UserError("give exactly one of --swarm FILE or --scenario NAME")
    if swarm is not None:
        from cli.swarm_file import load_swarm_file

        cfg, _ = load_swarm_file(swarm, overrides)
    else:
        from cli.cmd_scenario import _load

        cfg = _load(scenario, overrides)
    typer.echo(dumps(to_dict(cfg), show_unset=True), nl=False)
