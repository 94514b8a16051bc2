"""`dinerf-agent split` and `dinerf-agent inspect` through the typer app, errors as one line."""

from __future__ import annotations

import json

from typer.testing import CliRunner

import cli.cmd_data  # noqa: F401  (registers the commands)
from cli.main import app

runner = CliRunner()


def test_split_writes_the_folders_and_prints_a_table(tmp_path):
    out = tmp_path / "split"
    res = runner.invoke(app, ["split", "--data", "procedural:views=40,width=16", "--robots", "2", "--out", str(out),
                              "--overlap", "0.2", "--depth-prior", "scaled", "--frame", "offset"])
    assert res.exit_code == 0, res.output
    assert "robot" in res.output and "overlap" in res.output and "(ref)" in res.output
    for name in ("robot1/transforms.json", "robot2/transforms.json", "eval/transforms.json", "truth.json",
                 "split.json", "scene.json"):
        assert (out / name).is_file(), name
    split = json.loads((out / "split.json").read_text())
    assert split["config"]["frame"] == "offset" and split["eval"]["views"][:2] == ["view_000", "view_008"]
    again = runner.invoke(app, ["split", "--data", "procedural:views=40,width=16", "--out", str(out)])
    assert again.exit_code == 2 and "--force" in again.output


def test_inspect_reports_what_it_found(tmp_path):
    res = runner.invoke(app, ["inspect", "--data", "procedural:views=6,width=16"])
    assert res.exit_code == 0, res.output
    for word in ("views", "16 x 16", "RGBA", "intrinsics", "depth", "scene box"):
        assert word in res.output


def test_a_wrong_path_is_one_clear_line_and_exit_code_2(tmp_path):
    for cmd in (["inspect", "--data", str(tmp_path / "nope")],
                ["split", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]):
        res = runner.invoke(app, cmd)
        assert res.exit_code == 2
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error:") and "expected transforms.json" in lines[0]
    res = runner.invoke(app, ["split", "--data", "procedural:views=8,width=8", "--out", str(tmp_path / "o"),
                              "--frame", "sideways"])
    assert res.exit_code == 2 and "frame must be one of" in res.output
