"""Where a ray's samples go as a field forms: the occupancy grid and the sampler over training (issue 42).

    .venv/bin/python benchmarks/bench_grid.py --scene room100 --steps 600 \\
        --variant occupancy.decay=0.95,occupancy.density_threshold=1 --variant occupancy.density_threshold=1 --variant none

One model per variant: the scene's ``fitted`` configuration (benchmarks/bench_defaults.py: the
default for the capture, true poses, one thread) with the variant's ``[training.train]`` settings
over it, trained on the scene's training views and scored on its held-out ones. Every ``--every``
steps, on 2048 training rays marched as the trainer marches them: the grid's open fraction, the
candidates a ray has in open cells, the samples kept for the differentiable pass (in front of
early termination) and how many of those lie in the linear box, and the share of rays that end
opaque. A variant is ``key=value[,key=value...]`` (dotted below ``training.train``); ``none`` is the
default.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from agent.data.loaders import load_views  # noqa: E402
from agent.nerf.rays import pixel_centre, pixel_rays, transform_rays  # noqa: E402
from agent.nerf.sampler import march, segment_starts  # noqa: E402
from agent.trainer import RobotTrainer, TrainConfig  # noqa: E402
from benchmarks.bench_defaults import SCENES, centralised, config  # noqa: E402
from cli.config import apply_overrides  # noqa: E402

PROBE_RAYS = 2048


def variant_config(scene: str, views, steps: int, variant: str) -> TrainConfig:
    cfg = config(scene, "fitted", views, steps)
    return cfg if variant == "none" else apply_overrides(cfg, variant.split(","))


@torch.no_grad()
def probe(trainer: RobotTrainer, generator: torch.Generator) -> dict[str, float]:
    """Where the samples of ``PROBE_RAYS`` training rays go now."""
    field, grid, cfg = trainer.field, trainer.grid, trainer.cfg
    img, row, col, _ = trainer._sample_pixels(PROBE_RAYS)
    rays = pixel_rays(trainer.cameras_shared()[img], trainer.camera_intrinsics()[img], pixel_centre(col.float()),
                      pixel_centre(row.float()))
    box = transform_rays(rays, trainer.box_from_shared)
    lw = trainer.level_weights(trainer.step)
    to_grid = field.to_grid if field.cfg.unbounded else None

    def density(x: torch.Tensor) -> torch.Tensor:
        return field.density(x if to_grid is None else to_grid(x), lw)[0]

    jitter = torch.rand(PROBE_RAYS, generator=generator)
    kept = march(box.origins, box.directions, grid, density, cfg.march, jitter, True, to_grid=to_grid)
    candidates = march(box.origins, box.directions, grid, density, cfg.march, jitter, False, to_grid=to_grid)
    x = box.origins[kept.ray_index] + kept.t_mid[:, None] * box.directions[kept.ray_index]  # [S, 3]
    depth = torch.zeros(PROBE_RAYS, dtype=torch.float64).index_add_(
        0, kept.ray_index, (density(x) * kept.dt).double())  # [R] optical depth of the kept samples
    _, counts = segment_starts(kept.ray_index, PROBE_RAYS)
    return {"open": grid.occupied_fraction, "candidates": len(candidates) / PROBE_RAYS,
            "kept": len(kept) / PROBE_RAYS, "kept_p90": float(counts.float().quantile(0.9)),
            "in_box": float((x.abs().amax(-1) <= 1).float().mean()) if len(kept) else 0.0,
            "opaque": float((depth > 4.6).float().mean())}  # transmittance below 1%


def run_variant(scene: str, views, steps: int, every: int, variant: str) -> dict:
    trainer, test = centralised(scene, views, variant_config(scene, views, steps, variant))
    generator = torch.Generator().manual_seed(1)
    seconds = 0.0
    for step in range(steps + 1):
        if step % every == 0 or step == steps:
            p = probe(trainer, generator)
            print(f"  {variant:28s} step {step:5d}  open {p['open']:.3f}  candidates/ray {p['candidates']:6.1f}  "
                  f"kept/ray {p['kept']:6.1f} (p90 {p['kept_p90']:.0f}, {p['in_box']:.0%} in the box)  "
                  f"opaque rays {p['opaque']:.0%}", flush=True)
        if step < steps:
            t0 = time.perf_counter()
            trainer.train_step()
            seconds += time.perf_counter() - t0
    scores = trainer.evaluate(views.subset(test), frame="local", with_ssim=False)
    return {"variant": variant, "s_per_step": seconds / steps, "kept_end": p["kept"], "open_end": p["open"],
            "psnr": sum(scores["psnr"]) / len(scores["psnr"])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="room100", choices=sorted(SCENES))
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--variant", action="append", default=None,
                    help="key=value[,key=value...] below training.train, or none")
    args = ap.parse_args()
    torch.set_num_threads(1)
    views = load_views(SCENES[args.scene][0], width=SCENES[args.scene][1])
    for v in args.variant or []:  # a misspelt key is one line now, not a traceback after the first model's run
        try:
            variant_config(args.scene, views, args.steps, v)
        except ValueError as e:  # ConfigError, or a value out of range
            raise SystemExit(f"--variant {v}: {e}") from None
    rows = [run_variant(args.scene, views, args.steps, args.every, v) for v in (args.variant or ["none"])]
    print(f"\n{args.scene}, {args.steps} steps:")
    for r in rows:
        print(f"  {r['variant']:28s} {r['s_per_step']:.3f} s/step  kept/ray at the end {r['kept_end']:.1f}  "
              f"grid open {r['open_end']:.2f}  PSNR {r['psnr']:.2f} dB")


if __name__ == "__main__":
    main()
