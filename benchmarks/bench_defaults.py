"""Defaults that fit the data (issue 42): seconds per step, samples per ray, PSNR at equal steps, render time.

    .venv/bin/python benchmarks/bench_defaults.py                  # every scene, every config (~1.5 h on 2 cores)
    .venv/bin/python benchmarks/bench_defaults.py --scenes room48 --steps 200   # a quick look

One model per (scene, config), trained on the scene's training views with the true poses (the
centralised model: the same trainer a robot runs, so a step costs what a robot's step costs), on
one thread as a robot of a 2-robot swarm on 2 cores would have, then scored on the held-out views:

- scenes: ``room48`` and ``room100`` (the procedural object in a textured room, RGB: an unbounded
  field; 60 views on a 90 deg arc, every 6th held out, as ``room-2-arc``), ``maryrose`` (128 px,
  its masks as alpha: bounded; every 8th held out) and ``lego`` (100 px, alpha; every 8th held out);
  the last two need ../shared/data and are skipped with a note without it;
- configs: ``fitted`` (what ``agent.defaults`` gives the capture: the default now), ``tuned`` (the
  settings the scenarios set by hand before it: room-2-arc's field, grid and rays for the room;
  the dataclass defaults for lego and maryrose, whose scenarios set none) and ``before`` (the
  dataclass defaults and sampler of before issue 42, whatever the capture). ``before`` on the room
  costs seconds a step, so it trains ``--before-steps`` (200) steps, and its PSNR is at those steps.

Seconds per step is the mean over the run (grid updates included) and over its last quarter;
samples per ray (what enters the differentiable pass) over the first and the last quarter; render
seconds per held-out view is the evaluation's (no gradient). Timings need an otherwise idle machine:
run it alone (``flock /tmp/dinerf-heavy.lock ...`` where other heavy jobs take the same lock).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from agent.config_io import from_dict, merge_tables  # noqa: E402
from agent.data.loaders import load_views  # noqa: E402
from agent.data.split import estimate_scene_box, test_indices  # noqa: E402
from agent.defaults import Capture, fit_train  # noqa: E402
from agent.geometry import box_from_center  # noqa: E402
from agent.trainer import RobotTrainer, TrainConfig  # noqa: E402

SHARED = Path(os.environ.get("DINERF_SHARED_DATA") or ROOT.parent / "shared/data")
SCENES = {  # name: (dataset, width, test_every)
    "room48": ("procedural:views=60,width=48,room=1,arc=90", 48, 6),
    "room100": ("procedural:views=60,width=100,room=1,arc=90", 100, 6),
    "maryrose": (str(SHARED / "maryrose"), 128, 8),
    "lego": (str(SHARED / "nerf_synthetic/lego"), 100, 8),
}
# room-2-arc's [training.train] before agent.defaults (the quickstart's field, a 96^3 grid, 1024 rays)
ROOM_TUNED = {"rays_per_step": 1024, "field": {"density_hidden": 32, "color_hidden": 32,
              "grid": {"log2_hashmap_size": 14, "num_levels": 12, "max_resolution": 256}},
              "occupancy": {"resolution": 96, "warmup_steps": 64, "update_every": 16},
              "march": {"skip_visibility_above": 0.6}}
BEFORE = {"march": {"skip_visibility_above": 0.6}}  # the sampler's rule before issue 42


def config(scene: str, name: str, views, steps: int) -> TrainConfig:
    capture = Capture(unbounded=views.shows_surroundings, width=views.width)
    table = {"fitted": fit_train({}, capture),
             "tuned": ROOM_TUNED if scene.startswith("room") else BEFORE,
             "before": BEFORE}[name]
    cfg = from_dict(TrainConfig, merge_tables(table, {}), "train")
    return dataclasses.replace(cfg, total_steps=steps, pose=dataclasses.replace(cfg.pose, mode="fixed"))


def centralised(scene: str, views, cfg: TrainConfig) -> tuple[RobotTrainer, list[int]]:
    """The centralised model of the scene's training views, and the held-out views' indices."""
    test = test_indices(len(views), SCENES[scene][2])
    train = [i for i in range(len(views)) if i not in set(test)]
    centre, half, _ = estimate_scene_box(views, cfg.field.unbounded)
    return RobotTrainer(views.subset(train), cfg, box_from_center(centre, half)), test


def run_one(scene: str, name: str, steps: int, views) -> dict:
    cfg = config(scene, name, views, steps)
    trainer, test = centralised(scene, views, cfg)
    times, samples = [], []
    for _ in range(steps):
        t0 = time.perf_counter()
        s = trainer.train_step()
        times.append(time.perf_counter() - t0)
        samples.append(s["samples"])
    t0 = time.perf_counter()
    scores = trainer.evaluate(views.subset(test), frame="local", with_ssim=False)
    render_s = (time.perf_counter() - t0) / len(test)
    q = max(steps // 4, 1)
    return {"scene": scene, "config": name, "steps": steps, "s_per_step": sum(times) / steps,
            "s_per_step_last_quarter": sum(times[-q:]) / q, "samples_per_ray_first_quarter": sum(samples[:q]) / q,
            "samples_per_ray_last_quarter": sum(samples[-q:]) / q, "psnr": sum(scores["psnr"]) / len(scores["psnr"]),
            "render_s_per_view": render_s, "field": dataclasses.asdict(cfg.field), "rays_per_step": cfg.rays_per_step,
            "occupancy": cfg.occupancy.resolution, "skip_visibility_above": cfg.march.skip_visibility_above}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--configs", default="fitted,tuned,before")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--before-steps", type=int, default=200, help="steps of 'before' on the room (seconds a step)")
    ap.add_argument("--out", type=Path, default=None, help="also write the rows as JSON lines here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"load average {os.getloadavg()[0]:.2f}", flush=True)
    rows = []
    for scene in args.scenes.split(","):
        dataset = SCENES[scene][0]
        if not dataset.startswith("procedural") and not Path(dataset).exists():
            print(f"{scene}: skipped, {dataset} not found", flush=True)
            continue
        done: dict[str, dict] = {}
        views = load_views(dataset, width=SCENES[scene][1])
        for name in args.configs.split(","):
            steps = args.before_steps if name == "before" and scene.startswith("room") else args.steps
            key = json.dumps(dataclasses.asdict(config(scene, name, views, steps)), sort_keys=True)
            if key in done:  # the same settings (lego: tuned = before): one run, two rows
                rows.append({**done[key], "config": name})
            else:
                rows.append(done.setdefault(key, run_one(scene, name, steps, views)))
            r = rows[-1]
            print(f"{scene:9s} {name:7s} {r['steps']:5d} steps  {r['s_per_step']:.3f} s/step "
                  f"(last quarter {r['s_per_step_last_quarter']:.3f})  samples/ray {r['samples_per_ray_first_quarter']:.1f}"
                  f" -> {r['samples_per_ray_last_quarter']:.1f}  PSNR {r['psnr']:.2f} dB  render {r['render_s_per_view']:.2f}"
                  " s/view", flush=True)
            if args.out is not None:
                with args.out.open("a") as f:
                    f.write(json.dumps(r) + "\n")
    print(f"load average {os.getloadavg()[0]:.2f}", flush=True)


if __name__ == "__main__":
    main()
