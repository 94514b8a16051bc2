"""``dinerf-agent baseline``: the centralised model on all views, with renders and metrics."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import typer

from cli.errors import friendly_errors
from cli.main import app
from cli.options import DATA_HELP, SET_HELP, check_output_folder, load_train_config, progress_bar, set_threads


@app.command()
@friendly_errors
def baseline(
    data: str = typer.Option(..., "--data", help=DATA_HELP),
    out: Path = typer.Option(Path("runs/baseline"), "--out", help="Output folder."),
    steps: int = typer.Option(2000, help="Optimiser steps."),
    width: int = typer.Option(None, help="Downscale images to this width."),
    test_every: int = typer.Option(8, help="Test views 0, k, 2k, ... are held out for evaluation; 0 = none."),
    config: Path = typer.Option(None, "--config", help="TOML file with a \\[train] table."),
    overrides: list[str] = typer.Option([], "--set", help=SET_HELP),
    threads: int = typer.Option(2, help="CPU threads for torch."),
    renders: int = typer.Option(4, help="How many held-out views to save as PNG (prediction | truth)."),
) -> None:
    """Train one model on all views (the paper's centralised baseline); report PSNR/SSIM on held-out views."""
    import torch

    from agent.checkpoint import CHECKPOINT, save_baseline
    from agent.evaluation import evaluate_heldout, train_baseline
    from agent.data.folder import write_png
    from agent.data.loaders import load_views

    from agent.defaults import Capture

    set_threads(threads)
    check_output_folder(out, "--out")
    load_train_config(config, overrides, total_steps=steps)  # a wrong key is said before the images load
    views = load_views(data, width=width)
    # one model on its own images: they are the capture whose settings it gets (agent.defaults)
    cfg = load_train_config(config, overrides, total_steps=steps,
                            capture=Capture(unbounded=views.shows_surroundings, width=views.width))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with progress_bar() as bar:
        task = bar.add_task("training", total=cfg.total_steps)
        run = train_baseline(views, cfg, test_every, on_step=lambda i: bar.update(task, completed=i))
    train_seconds = time.perf_counter() - t0
    scores = evaluate_heldout(run, views)
    test_views = views.subset(run.test_indices)

    (out / "renders").mkdir(exist_ok=True)
    gt = test_views.rgb(1.0)
    for i in range(min(renders, len(test_views))):
        pred = run.trainer.render(test_views.c2w[i], test_views.intrinsics[i], test_views.width, test_views.height)
        side = torch.cat([pred["rgb"].cpu(), gt[i]], 1).numpy()
        write_png(out / "renders" / f"{test_views.names[i]}.png", side)
    save_baseline(out / CHECKPOINT, run.trainer, cfg)

    metrics = {
        "data": str(data),
        "resolution": [views.width, views.height],
        "steps": cfg.total_steps,
        "train_views": len(run.train_indices),
        "heldout_views": [views.names[i] for i in run.test_indices],
        "heldout_rule": f"every {test_every}th view (indices 0, {test_every}, ...)",
        "psnr": statistics.fmean(scores["psnr"]),
        "ssim": statistics.fmean(scores["ssim"]),
        "psnr_per_view": scores["psnr"],
        "ssim_per_view": scores["ssim"],
        "seconds_train": train_seconds,
        "seconds_per_step_median": statistics.median(run.step_seconds),
        "threads": threads,
        "box_source": run.box_source,
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    typer.echo(
        f"held-out PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.3f} on {len(run.test_indices)} views; "
        f"{metrics['seconds_per_step_median']:.3f} s/step median, {train_seconds:.0f} s; wrote {out}/"
    )

