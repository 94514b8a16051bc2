"""What a real scenario run's report must show in its figures, read back from report.json and orbit.gif."""

from __future__ import annotations

from pathlib import Path

import numpy as np

POSE_PANELS = {"rotation_error_deg", "translation_error"}


def scored_rounds(report: dict, robot: str) -> list[int]:
    """The rounds report.json has held-out scores for."""
    return sorted(int(k) for k, v in report["robots"][robot]["rounds"].items() if v.get("psnr") is not None)


def check_figures(out: Path, report: dict, orbit_frames: int, pose_panels: bool, all_robots: bool) -> None:
    import imageio.v3 as iio

    figs = report["figures"]
    panels = set(figs["convergence"]["panels"])
    assert {"psnr", "psnr_others_only", "disagreement", "loss"} <= panels
    assert (POSE_PANELS <= panels) if pose_panels else not (POSE_PANELS & panels), panels
    assert figs["poses_known"] is (not pose_panels)
    md = (out / "report.md").read_text()
    assert ("no pose panels" in md) is (not pose_panels)
    robots = sorted(report["robots"])
    for r in robots:  # one point per scored round, every curve
        rounds = scored_rounds(report, r)
        assert rounds and figs["convergence"]["points"]["psnr"][r] == rounds
        assert figs["convergence"]["points"]["psnr_others_only"][r] == rounds
        if len(robots) > 1:
            assert figs["convergence"]["points"]["disagreement"][r] == rounds
        assert figs["convergence"]["points"]["loss"][r] == sorted(int(k) for k in report["robots"][r]["rounds"])
    assert (out / "convergence.png").read_bytes()[:4] == b"\x89PNG"

    orbit = figs["orbit"]
    assert "![orbit](orbit.gif)" in md and orbit["robots"] == ([int(r) for r in robots] if all_robots else [1])
    gif = iio.imread(out / "orbit.gif", index=None)  # [N, H, W, 3]
    assert gif.shape[0] == orbit_frames == orbit["frames"] and list(gif.shape[1:3]) == orbit["size"], gif.shape
    assert gif.std() > 10, "a constant image"
    steps = [np.abs(gif[k].astype(int) - gif[k + 1].astype(int)).mean() for k in range(orbit_frames - 1)]
    assert min(steps) > 0.1, f"the orbit does not move: {steps}"
