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
        from agent.data.loaders import load_views
        from cli.cmd_scenario import _load
        from cli.swarm_file import capture_of, fit_to_capture

        cfg = _load(scenario, overrides)
        # the settings its images call for (agent.defaults), as the run fits them after its split
        views = load_views(cfg.resolved_dataset(), width=cfg.split.robot_image_width or cfg.width)
        capture = capture_of({"unbounded": views.shows_surroundings, "width": views.width}, cfg.training)
        cfg = fit_to_capture(cfg, cfg.given_train, capture)
    doc = to_dict(cfg)
    doc.pop("given_train", None)  # a scenario's own [training.train], already inside [training.train]
    typer.echo(dumps(doc, show_unset=True), nl=False)
