"""Issue 20's distortion benchmark: what a lens costs once undone at load time, and what ignoring it costs.

Three centralised models per seed on the procedural scene, the same cameras and steps:

- ``pinhole``: photographed through a pinhole lens (the reference);
- ``undistorted``: photographed through a lens with ``--k1`` (OpenCV radial-tangential),
  undone at load time as every loader does (:func:`agent.data.frames.undistort_views`), at the
  native size before the downscale (``--native-scale 1`` undoes it at the training size, where
  the resampling itself blurs);
- ``ignored``: the same distorted photographs loaded as if pinhole (``undistort=False``).

Every model is scored on the pinhole capture's held-out views (the scene as it is), so the
difference to ``pinhole`` is what the lens still costs.

    nice .venv/bin/python benchmarks/bench_distortion.py --k1 0.06 --seeds 0,1
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.data.images import resize_views  # noqa: E402
from agent.data.loaders import load_views, parse_procedural_spec  # noqa: E402
from agent.defaults import Capture  # noqa: E402
from agent.evaluation.baselines import train_baseline  # noqa: E402
from agent.metrics import finite_mean  # noqa: E402
from agent.trainer import TrainConfig  # noqa: E402
from cli.config import apply_overrides  # noqa: E402
from cli.scenario.spec import find_scenario, load_scenario  # noqa: E402
from cli.swarm_file import fit_to_capture  # noqa: E402

CASES = ("pinhole", "undistorted", "ignored")


def load_case(case: str, spec: str, k1: float, native_scale: int):
    """The capture as a loader gives it: photographed at ``native_scale`` x the training width (a
    camera's native size), the lens undone there (or not), then downscaled, as for a real capture."""
    width = parse_procedural_spec(spec).width
    lens = "" if case == "pinhole" else f",k1={k1}"
    native = load_views(f"{spec}{lens}", width=width * native_scale, undistort=case == "undistorted")
    return resize_views(native, width)


def run_case(case: str, spec: str, k1: float, native_scale: int, cfg: TrainConfig, test_every: int, truth) -> dict:
    t0 = time.time()
    views = load_case(case, spec, k1, native_scale)
    run = train_baseline(views, cfg, test_every=test_every)
    scores = run.trainer.evaluate(truth.subset(run.test_indices), frame="local", with_ssim=True)
    return {"psnr": finite_mean(scores["psnr"]), "ssim": finite_mean(scores["ssim"]),
            "seconds": time.time() - t0, "notes": list(views.meta.get("notes", []))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="procedural:views=60,width=48", help="a procedural spec (no k1)")
    ap.add_argument("--k1", type=float, default=0.06)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--native-scale", type=int, default=4,
                    help="photograph at this many times the width, undo the lens there, then downscale")
    ap.add_argument("--seeds", default="0,1", help="training seeds (sampling), one model per case and seed")
    ap.add_argument("--test-every", type=int, default=6)
    ap.add_argument("--set", action="append", default=[], help="TrainConfig override of the quickstart's")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if not args.data.startswith("procedural") or "k1=" in args.data:
        raise SystemExit("--data must be a procedural spec without k1 (the benchmark adds the lens)")
    torch.set_num_threads(args.threads)
    truth = load_case("pinhole", args.data, args.k1, args.native_scale)
    # the quickstart's field and sampler: what its 48 px images with alpha call for (agent.defaults)
    quickstart = load_scenario(find_scenario("quickstart"))
    small = fit_to_capture(quickstart, quickstart.given_train, Capture(unbounded=False, width=48)).training.train
    base = apply_overrides(small, [f"total_steps={args.steps}", *args.set])
    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"{args.data}, k1 = {args.k1}, photographed at {args.native_scale}x the width: {args.steps} steps per "
          f"model, seeds {seeds}; scored on the pinhole capture's held-out views (every {args.test_every}th)", flush=True)
    results: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "cases": {c: [] for c in CASES}}
    for seed in seeds:
        cfg = replace(base, seed=seed)
        for case in CASES:
            r = run_case(case, args.data, args.k1, args.native_scale, cfg, args.test_every, truth)
            results["cases"][case].append(r)
            print(f"  seed {seed} {case:12s} PSNR {r['psnr']:.2f} dB, SSIM {r['ssim']:.3f} ({r['seconds']:.0f} s)",
                  flush=True)
    ref = statistics.fmean(r["psnr"] for r in results["cases"]["pinhole"])
    print("\nsummary (mean over seeds; difference to the pinhole capture):")
    for case in CASES:
        mean = statistics.fmean(r["psnr"] for r in results["cases"][case])
        per_seed = " / ".join(f"{r['psnr']:.2f}" for r in results["cases"][case])
        print(f"  {case:12s} {mean:6.2f} dB ({mean - ref:+.2f})  per seed {per_seed}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
