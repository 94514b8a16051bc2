"""Command-line conventions: --version, log levels, `config show` printing what a command runs with."""

from __future__ import annotations

import logging
import tomllib

import pytest
from typer.testing import CliRunner

import cli.main
from cli.config import to_dict
from cli.logs import level_from
from cli.swarm_file import load_swarm_file

cli.main._register()
runner = CliRunner()


def test_version_is_the_installed_package_version():
    from importlib import metadata

    res = runner.invoke(cli.main.app, ["--version"])
    assert res.exit_code == 0 and res.stdout.strip() == f"dinerf-agent {metadata.version('dinerf')}"


@pytest.mark.parametrize("verbose, quiet, env, level", [
    (0, 0, None, logging.INFO), (1, 0, None, logging.DEBUG), (0, 1, None, logging.WARNING),
    (0, 2, None, logging.ERROR), (0, 0, "warning", logging.WARNING), (1, 0, "WARNING", logging.INFO),
    (0, 5, "debug", logging.ERROR),
])
def test_log_level_from_flags_and_environment(verbose, quiet, env, level):
    assert level_from(verbose, quiet, env) == level


def test_an_unknown_log_level_is_one_line(monkeypatch):
    monkeypatch.setenv("DINERF_LOG", "loud")
    res = runner.invoke(cli.main.app, ["config", "show", "--scenario", "quickstart"])
    assert res.exit_code == 2 and res.stderr.strip().splitlines() == [
        "error: DINERF_LOG='loud': expected one of debug, info, warning, error"]


def test_config_show_prints_the_effective_swarm_config_with_its_defaults(tmp_path):
    out = tmp_path / "split"
    res = runner.invoke(cli.main.app, ["split", "--data", "procedural:views=8,width=8", "-n", "2", "--out", str(out)])
    assert res.exit_code == 0, res.output
    shown = runner.invoke(cli.main.app, ["config", "show", "--swarm", str(out / "swarm.toml"),
                                         "--set", "training.rounds=7"])
    assert shown.exit_code == 0, shown.output
    printed = tomllib.loads(shown.stdout)
    cfg, _ = load_swarm_file(out / "swarm.toml", ["training.rounds=7"])
    assert printed["training"]["rounds"] == 7
    assert printed["daemon"]["round_timeout_s"] == cfg.daemon.round_timeout_s  # a default, written out
    written = tmp_path / "shown.toml"
    written.write_text(shown.stdout)
    again, _ = load_swarm_file(written)
    assert to_dict(again) == to_dict(cfg), "what config show prints runs as the same configuration"


def test_config_show_needs_exactly_one_source():
    res = runner.invoke(cli.main.app, ["config", "show"])
    assert res.exit_code == 2 and "exactly one of --swarm" in res.stderr
