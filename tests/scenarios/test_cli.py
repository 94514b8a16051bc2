"""`dinerf-agent scenario ...` as a user types it: one-line errors, and a tiny real run on loopback."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from agent.checkpoint import RunFolder
from tests.agent_cli import agent
from tests.scenarios.report_checks import check_figures, scored_rounds

ROOT = Path(__file__).resolve().parents[2]

TINY = """
[scenario]
name = "cli-tiny"
dataset = "procedural:views=24,width=24"
robots = 2
credit = "Photography: a test"
[split]
overlap = 0.1
frame = "world"
test_every = 6
[topology]
kind = "full"
[training]
rounds = 3
steps_per_round = 6
own_holdout_every = 0
[training.train]
rays_per_step = 256
[training.train.field.grid]
log2_hashmap_size = 12
num_levels = 8
max_resolution = 128
[training.train.occupancy]
resolution = 32
warmup_steps = 16
update_every = 8
[daemon]
round_timeout_s = 20
eval_every = 0
[baseline]
enabled = true
[report]
ssim = false
render_views = 2
orbit_frames = 12
orbit_all_robots = true
"""


def one_line_error(p: subprocess.CompletedProcess) -> str:
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    lines = [l for l in p.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in p.stderr, p.stderr
    return lines[0]


def test_list_shows_the_shipped_scenarios():
    p = agent("scenario", "list")
    assert p.returncode == 0, p.stderr
    assert "quickstart" in p.stdout and "lego-5-ring" in p.stdout


def test_errors_are_one_line(tmp_path):
    assert "no scenario 'nope'" in one_line_error(agent("scenario", "run", "nope"))
    bad = tmp_path / "bad.toml"
    bad.write_text("[scenario\nname = 1\n")
    assert "not valid TOML" in one_line_error(agent("scenario", "run", str(bad)))
    typo = tmp_path / "typo.toml"
    typo.write_text(TINY.replace("steps_per_round", "step_per_round"))
    assert "step_per_round" in one_line_error(agent("scenario", "run", str(typo)))
    cut = tmp_path / "cut.toml"
    cut.write_text(TINY + "[faults]\ncut = [{ link = [1, 2], from_round = 1 }]\n")
    assert "--mode netns" in one_line_error(agent("scenario", "run", str(cut), "--mode", "local"))
    missing = tmp_path / "missing.toml"
    missing.write_text(TINY.replace('"procedural:views=24,width=24"', '"../no/such/lego"'))
    assert "dataset '../no/such/lego' not found" in one_line_error(agent("scenario", "run", str(missing)))
    assert "run.json" in one_line_error(agent("scenario", "report", str(tmp_path)))


@pytest.mark.slow
def test_tiny_run_on_loopback_writes_the_report(tmp_path):
    scen = tmp_path / "scenario.toml"
    scen.write_text(TINY)
    out = tmp_path / "out"
    # the pose learnt (SE(3) from the identity) although the frames are shared: its error is measured, so plotted
    p = agent("scenario", "run", str(scen), "--out", "out", "--set", "training.train.pose.mode=se3",
              cwd=tmp_path)  # relative, as in the README
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "completed: all robots finished" in p.stdout
    report = json.loads((out / "report.json").read_text())
    for i in ("1", "2"):
        r = report["robots"][i]
        assert r["final_round"] == 3 and r["final"]["psnr"] > 5 and r["rounds_logged"] == 3
        assert r["final"]["psnr_own_views"] > 5 and "psnr_own_views" not in r["rounds"]["2"]  # final round only
        assert set(r["rounds"]) == {"1", "2", "3"}
    assert report["links_bytes"]["1->2"] > 0 and report["links_bytes"]["2->1"] > 0
    assert report["baseline"]["centralised"]["psnr"] > 5 and set(report["baseline"]["alone"]) == {"1", "2"}
    # the robots' model, as agent.defaults fitted it to the capture (the scenario leaves the MLP widths unset)
    robot_field = RunFolder(out / "robots" / "1", create=False).load(1).trainer["field"]
    assert report["baseline"]["centralised"]["field_parameters"] == sum(t.numel() for t in robot_field.values())
    md = (out / "report.md").read_text()
    assert "| robot | round | PSNR all" in md and "Centralised model" in md and "Fit of each robot's own training views" in md
    assert "- data credit: Photography: a test" in md
    for png in ("convergence.png", "renders.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    check_figures(out, report, orbit_frames=12, pose_panels=True, all_robots=True)
    assert scored_rounds(report, "1") == [1, 2, 3]  # eval_every = 1: every round
    again = agent("scenario", "run", str(scen), "--out", str(out))
    assert "--force" in one_line_error(again)
