"""What the scenario report's figures cost on a finished run: scoring every k-th round, and orbit.gif.

Scoring a kept round renders every held-out view once per robot (``agent.evaluation.score_run``);
the orbit renders ``--orbit-frames`` views per robot it shows (``cli.scenario.figures.write_orbit``).
The baselines, which dominate the report's time, are not trained here.

    .venv/bin/dinerf-agent scenario run quickstart --out runs/quickstart
    .venv/bin/python benchmarks/bench_report.py runs/quickstart --every 5,3,2,1 [--workers 1]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="the output folder of a `scenario run`")
    ap.add_argument("--every", default="5,2,1", help="eval_every values to time, comma-separated")
    ap.add_argument("--orbit-frames", type=int, default=36)
    ap.add_argument("--workers", type=int, default=2, help="scoring processes (the report's report.workers)")
    args = ap.parse_args()

    import torch

    from agent.evaluation import ScoringOptions, score_run
    from cli.scenario.figures import write_orbit
    from cli.scenario.report import load_run_spec, swarm_run

    spec = load_run_spec(args.run)
    torch.set_num_threads(spec.report.threads)
    run = swarm_run(args.run, spec.ids)
    scores = None
    for every in (int(x) for x in args.every.split(",")):
        t = time.monotonic()
        scores = score_run(run, ScoringOptions(every=every, with_ssim=spec.report.ssim,
                                               fit_pose_steps=spec.report.fit_heldout_poses_steps,
                                               own_views_every=spec.report.own_views_every), workers=args.workers)
        print(f"eval_every={every}, {args.workers} workers: rounds {sorted(scores.rounds[spec.reference_id])} x {len(spec.ids)} robots "
              f"scored in {time.monotonic() - t:.1f} s", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for robots in ([spec.reference_id], spec.ids) if args.orbit_frames else ():
            path = Path(tmp) / "orbit.gif"
            o = write_orbit({i: scores.finals[i] for i in robots}, spec.reference_id, args.orbit_frames,
                            scores.evalset.views.width, path)
            print(f"orbit of robots {robots}: {o['frames']} frames, {o['size'][1]}x{o['size'][0]} px, "
                  f"{o['seconds']:.1f} s, {path.stat().st_size / 1e3:.0f} kB", flush=True)


if __name__ == "__main__":
    main()
