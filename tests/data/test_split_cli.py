"""Every split option from the command line (`dinerf-agent split`) and from scenario.toml's [split]."""

from __future__ import annotations

import json

import cv2
import pytest
from typer.testing import CliRunner

import cli.cmd_data  # noqa: F401  (registers the commands)
from cli.config import ConfigError
from cli.main import app
from cli.scenario.spec import load_scenario

runner = CliRunner()


def test_cli_reaches_every_split_option(tmp_path):
    out = tmp_path / "split"
    res = runner.invoke(app, ["split", "--data", "procedural:views=40,width=16,arc=90", "--robots", "2", "--out",
                              str(out), "--by", "trajectory", "--sector-start", "30", "--overlap", "0.2",
                              "--width", "8", "--robot-image-width", "16", "--set", "up=[0, 0, 1]",
                              "--set", "offset_rotation_deg=[0, 0, 90]"])
    assert res.exit_code == 0, res.output
    assert "trajectory" in res.output and "azimuths" in res.output
    split = json.loads((out / "split.json").read_text())
    cfg = split["config"]
    assert (cfg["by"], cfg["sector_start_deg"], cfg["up"], cfg["offset_rotation_deg"]) == ("trajectory", 30.0,
                                                                                           [0, 0, 1], [0, 0, 90])
    assert split["layout"] == "trajectory" and split["segment_margin_views"] > 0
    robot = cv2.imread(str(next((out / "robot1/images").glob("*.png"))))
    test = cv2.imread(str(next((out / "eval/images").glob("*.png"))))
    assert robot.shape[1] == 16 and test.shape[1] == 8, "robots at --robot-image-width, test views at --width"
    bad = runner.invoke(app, ["split", "--data", "procedural:views=8,width=8", "--out", str(tmp_path / "o"),
                              "--set", "sector_stat_deg=3"])
    assert bad.exit_code == 2 and "sector_stat_deg" in bad.output


def test_sector_cli_on_an_arc_no_longer_refuses(tmp_path):
    res = runner.invoke(app, ["split", "--data", "procedural:views=40,width=8,arc=90", "--robots", "2", "--out",
                              str(tmp_path / "s")])
    assert res.exit_code == 0, res.output
    split = json.loads((tmp_path / "s/split.json").read_text())
    assert split["layout"] == "arc" and sorted(r["count"] for r in split["robots"].values()) == [17, 18]


def test_scenario_split_table_takes_the_new_options(tmp_path):
    (tmp_path / "scenario.toml").write_text(
        '[scenario]\nname = "walk"\ndataset = "procedural:views=40,width=16,arc=120,room=1"\nrobots = 2\n\n'
        '[split]\nby = "trajectory"\noverlap = 0.1\nsector_start_deg = 45.0\n')
    spec = load_scenario(tmp_path)
    assert (spec.split.by, spec.split.overlap, spec.split.sector_start_deg) == ("trajectory", 0.1, 45.0)
    (tmp_path / "scenario.toml").write_text('[scenario]\nname = "x"\n\n[split]\nby = "spiral"\n')
    with pytest.raises(ConfigError, match="spiral"):
        load_scenario(tmp_path)
