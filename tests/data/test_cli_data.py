"""`dinerf-agent split` and `dinerf-agent inspect` through the typer app, errors as one line."""

from __future__ import annotations

import json
import re

import numpy as np
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


def _inspect(*args: str) -> str:
    res = runner.invoke(app, ["inspect", *args], env={"COLUMNS": "300"})  # wide: no wrapped rows
    assert res.exit_code == 0, res.output
    return res.output


def test_inspect_shows_llff_masks_bounds_and_the_box_source(tmp_path):
    from .test_llff import ring, write_llff
    from .test_masks import grey, soft_mask
    from .helpers import write_png

    write_llff(tmp_path, ring(), np.tile([2.5, 5.5], (5, 1)), folders=(("images_2", 2),))
    for i in range(5):
        write_png(tmp_path / "masks_2" / f"IMG_{i:02d}_mask.png", grey(soft_mask(i, 30, 40)))
    out = _inspect("--data", str(tmp_path), "--width", "20")
    for text in ("LLFF", "masks", "yes: 5 from masks_2/, composited as alpha; mean coverage", "distortion",
                 "none (pinhole cameras)", "near 2.500-2.500, far 5.500-5.500", "(from the near/far bounds)"):
        assert text in out, text
    assert "warning" not in out


def test_inspect_warns_about_rgb_without_masks_a_box_from_cameras_and_ignored_distortion(tmp_path):
    from .test_undistort import RADTAN, W, H, _nerfstudio

    _nerfstudio(tmp_path, "OPENCV", RADTAN, np.full((H, W, 3), 0.5))
    out = _inspect("--data", str(tmp_path))
    assert re.search(r"masks\s+│ no\s", out)
    assert "nerfstudio OPENCV: undistorted at load (OpenCV), pinhole intrinsics replaced" in out
    assert "lens distortion undone: nerfstudio OPENCV (k1 -0.28, k2 0.07, p1 0.0012, p2 -0.0018) undone at 96x72" in out
    assert "RGB images without alpha or masks" in out and "unbounded field" in out
    assert "scene box estimated from the cameras only" in out and "(from the cameras only)" in out
    out = _inspect("--data", str(tmp_path), "--no-undistort")
    assert "nerfstudio OPENCV: ignored (undistort=False)" in out and "lens distortion ignored (k1, k2, p1, p2)" in out
    assert "lens distortion ignored (nerfstudio OPENCV): rays miss their pixels" in out
