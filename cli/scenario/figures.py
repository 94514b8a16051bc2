"""The report's pictures: convergence curves, the render sheet, and an orbit GIF of the final models.

Each drawing function returns what it drew (the panels, the rounds of every curve, the GIF's
frames), which report.json keeps: the report can then be checked without reading pixels.

The pose panels are left out when the poses are known by construction (robots in the shared
frame, the pose fixed at the identity): the "error" there is float noise around 0, not a
measurement, and a panel of it reads as a result.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cli.scenario.spec import ScenarioSpec

__all__ = ["poses_known", "plot_convergence", "render_sheet", "write_orbit"]


@dataclass(frozen=True)
class Panel:
    key: str  # the per-round key of report.json's robots.<i>.rounds
    title: str
    ylabel: str
    log: bool = False
    pose: bool = False


PANELS = (
    Panel("psnr", "PSNR on all held-out views", "PSNR (dB)"),
    Panel("psnr_others_only", "PSNR on the views only other robots saw", "PSNR (dB)"),
    Panel("disagreement", "consensus disagreement (scored rounds)",
          r"$\|\theta_i - \bar\theta\| \,/\, \|\bar\theta\|$ (relative)", log=True),
    Panel("loss", "training loss on own rays (round mean)", "RGB MSE (+ depth, appearance terms)", log=True),
    Panel("rotation_error_deg", "pose: rotation error", "rotation error (deg)", pose=True),
    Panel("translation_error", "pose: translation error", "translation error (scene units)", pose=True),
)


def poses_known(spec: ScenarioSpec) -> bool:
    """Every robot's pose is the truth by construction: shared frames, fixed at the identity."""
    return (spec.frames == "shared" and spec.training.train.pose.mode == "fixed"
            and spec.daemon.initial_pose == "identity")


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _series(report: dict, robot: int, key: str) -> tuple[list[int], list[float]]:
    rounds = report["robots"][str(robot)]["rounds"]
    xs = sorted(int(k) for k, v in rounds.items() if isinstance(v.get(key), (int, float)) and not math.isnan(v[key]))
    return xs, [rounds[str(k)][key] for k in xs]


def _baseline_lines(ax, report: dict, ids: list[int], key: str) -> None:
    """The centralised model (black, dashed) and each robot alone (its colour, dotted), each labelled."""
    b = report.get("baseline")
    if not b or key not in ("psnr", "psnr_others_only"):
        return
    c = b["centralised"].get(key)
    if isinstance(c, (int, float)) and not math.isnan(c):
        ax.axhline(c, color="k", ls="--", lw=1.2, label=f"centralised ({b['steps']} steps)")
    for n, i in enumerate(ids):
        v = b.get("alone", {}).get(str(i), {}).get(key)
        if isinstance(v, (int, float)) and not math.isnan(v):
            ax.axhline(v, color=f"C{n}", ls=":", lw=1.2, label=f"robot {i} alone")


def plot_convergence(report: dict, ids: list[int], path: Path, show_pose: bool) -> dict:
    """Every per-round score against the round, one line per robot, the baselines as labelled lines.

    -> {"panels": [keys drawn], "points": {key: {robot: [rounds plotted]}}}"""
    plt = _pyplot()
    panels = [p for p in PANELS if show_pose or not p.pose]
    cols = 3 if len(panels) > 4 else 2
    fig, axes = plt.subplots(2, cols, figsize=(5 * cols, 8), squeeze=False)
    drawn: dict = {"panels": [p.key for p in panels], "points": {}}
    faults = report.get("faults", [])
    for ax, panel in zip(axes.flat, panels):
        drawn["points"][panel.key] = {}
        for n, i in enumerate(ids):
            xs, ys = _series(report, i, panel.key)
            drawn["points"][panel.key][str(i)] = xs
            if xs:
                ax.plot(xs, ys, color=f"C{n}", marker="o", ms=3, label=f"robot {i}")
        _baseline_lines(ax, report, ids, panel.key)
        for n, f in enumerate(faults):
            ax.axvline(f.get("swarm_round", 0), color="red", alpha=0.4, lw=1, label="fault" if n == 0 else None)
        if panel.log and any(drawn["points"][panel.key].values()):
            ax.set_yscale("log")
        ax.set_title(panel.title)
        ax.set_xlabel("round")
        ax.set_ylabel(panel.ylabel)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    known = "" if show_pose else "; poses known (shared frame, fixed): no pose panels"
    fig.suptitle(f"{report['scenario']}: convergence{known}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return drawn


def render_sheet(finals: dict, evalset, spec: ScenarioSpec, path: Path, baseline_renders=None) -> None:
    """Rows: ground truth, [centralised], each robot (its final model, in the shared frame); columns: views.

    baseline_renders: [V, H, W, 3] uint8, the centralised model's render of every held-out view."""
    plt = _pyplot()
    import torch

    n = min(spec.report.render_views, len(evalset.views))
    if n == 0 or not finals:
        return
    m = len(evalset.views)
    idx = sorted({round(j * m / n) % m for j in range(n)})
    gt = evalset.views.rgb(1.0)
    cams = evalset.shared_cameras()
    w, h = evalset.views.width, evalset.views.height
    rows: list[tuple[str, list]] = [("truth", [gt[j].numpy() for j in idx])]
    with torch.no_grad():
        if baseline_renders is not None:
            rows.append(("centralised", [baseline_renders[j] / 255.0 for j in idx]))
        for i in sorted(finals):
            rows.append((f"robot {i}", [finals[i].render(cams[j], evalset.views.intrinsics[j], w, h)["rgb"].cpu().numpy() for j in idx]))
    fig, axes = plt.subplots(len(rows), len(idx), figsize=(2.2 * len(idx), 2.2 * len(rows)), squeeze=False)
    for r, (label, imgs) in enumerate(rows):
        for c, img in enumerate(imgs):
            ax = axes[r][c]
            ax.imshow(img.clip(0, 1))
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(label)
            if r == 0:
                seen = evalset.seen_by[idx[c]]
                ax.set_title(f"{evalset.views.names[idx[c]]}\nseen by {seen or 'nobody'}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _labelled(row: np.ndarray, label: str) -> np.ndarray:
    """A robot's row of frames [N, H, W, 3] uint8 under a white strip with its name."""
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (row.shape[2], 12), "white")
    ImageDraw.Draw(strip).text((2, 0), label, fill="black")
    head = np.broadcast_to(np.asarray(strip), (len(row), 12, row.shape[2], 3))
    return np.concatenate([head, row], axis=1)


def write_orbit(finals: dict, reference: int, frames: int, width: int, path: Path, fps: float = 12.0,
                min_width: int = 240) -> dict:
    """Each robot's final field along one orbit of the reference's cameras, in the shared frame.

    One row per robot, colour | depth, its name above; scaled up (nearest) to at least
    ``min_width`` pixels so that a 48-pixel model is visible in a page.
    -> {"path", "frames", "robots", "size": [H, W], "render_size": [h, w], "seconds"}"""
    from agent.outputs.paths import OrbitConfig, trainer_orbit
    from agent.outputs.render import render_views, video_frames, write_frames

    t0 = time.monotonic()
    ref = reference if reference in finals else min(finals)
    c2w, k, w, h = trainer_orbit(finals[ref], OrbitConfig(frames=frames), width)
    rows = []
    for i in sorted(finals):
        row = np.stack(video_frames(render_views(finals[i], c2w, k, w, h)))  # [N, h, 2w, 3] colour | depth
        scale = max(1, math.ceil(min_width / row.shape[2]))
        rows.append(_labelled(row.repeat(scale, axis=1).repeat(scale, axis=2), f"robot {i}"))
    grid = np.ascontiguousarray(np.concatenate(rows, axis=1))  # [N, robots * (12 + scale h), scale 2w, 3]
    write_frames(path, grid, fps)
    return {"path": path.name, "frames": frames, "robots": sorted(finals), "orbit_of": ref,
            "size": list(grid.shape[1:3]), "render_size": [h, w], "seconds": time.monotonic() - t0}
