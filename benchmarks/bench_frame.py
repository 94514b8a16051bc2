"""How much a model's score depends on the frame it trains in: one centralised model, frames turned.

    flock /tmp/dinerf-heavy.lock nice python benchmarks/bench_frame.py RUN_DIR [--steps 1000]

RUN_DIR is a finished recorded scenario run (``scenario run room-2-bags --out RUN_DIR``; one round is
enough, only its bags' keyframes are used). The centralised model of the frames the robots kept, with
the true poses, is trained in several frames that differ by a rigid turn only: the world, robot 1's
odometry frame (a random 3D rotation of it), the world turned 30 and 45 deg about its up axis; each in
the box its own cameras call for, scored on the split's held-out views carried into that frame. Two
at a time, one thread each. What a single run's score is worth when the swarm and its baseline are
compared across frames.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FRAMES = ("world", "odom1", "yaw30", "yaw45")


def frame_from_world(evalset, name: str):
    """[4, 4] float64: the world -> the named frame."""
    import torch

    if name == "world":
        return torch.eye(4, dtype=torch.float64)
    if name == "odom1":
        return torch.linalg.inv(evalset.world_from_local(1))
    a = math.radians(float(name.removeprefix("yaw")))  # about the world's up axis (+z, the procedural scenes')
    turn = torch.eye(4, dtype=torch.float64)
    turn[0, 0] = turn[1, 1] = math.cos(a)
    turn[0, 1], turn[1, 0] = -math.sin(a), math.sin(a)
    return turn


def train_in_frame(out: Path, name: str, steps: int) -> dict:
    import torch

    from agent.data.split import estimate_scene_box
    from agent.data.views import Views
    from agent.evaluation.baselines import robots_kept_views
    from agent.evaluation.evalset import EvalSet
    from agent.geometry import box_from_center, transform_c2w
    from agent.metrics import finite_mean
    from agent.trainer import RobotTrainer
    from cli.scenario.report import load_run_spec, swarm_run

    torch.set_num_threads(1)
    spec = load_run_spec(out)
    training = spec.training
    run = swarm_run(out, spec.ids, True)
    evalset = EvalSet.from_dir(run.split_dir)
    to_frame = frame_from_world(evalset, name)
    views = robots_kept_views(run, training, lambda i: to_frame @ evalset.world_from_local(i))
    cfg = replace(training.train, total_steps=steps, seed=training.seed, init_seed=training.seed,
                  cameras=replace(training.train.cameras, enabled=False))
    center, half, _ = estimate_scene_box(views, cfg.field.unbounded)
    trainer = RobotTrainer(views, replace(cfg, pose=replace(cfg.pose, mode="fixed")), box_from_center(center, half))
    t = time.monotonic()
    trainer.train(steps)
    held = evalset.views
    held = Views(held.images, transform_c2w(to_frame, held.c2w.double()).float(), held.intrinsics, held.names)
    psnr = finite_mean(trainer.evaluate(held, frame="local", with_ssim=False)["psnr"])
    return {"frame": name, "steps": steps, "psnr": psnr, "views": len(views), "half_size": half,
            "seconds": time.monotonic() - t}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.child:
        print(json.dumps(train_in_frame(a.run_dir, a.child, a.steps)))
        return
    rows = []
    for pair in (FRAMES[:2], FRAMES[2:]):
        procs = [subprocess.Popen([sys.executable, __file__, str(a.run_dir), "--steps", str(a.steps), "--child", f],
                                  stdout=subprocess.PIPE, text=True) for f in pair]
        for proc in procs:
            text, _ = proc.communicate()
            if proc.returncode != 0:
                raise SystemExit(f"a child failed (exit {proc.returncode})")
            rows.append(json.loads(text.strip().splitlines()[-1]))
    for r in rows:
        print(f"  {r['frame']:6s} {r['steps']} steps on {r['views']} kept frames: PSNR {r['psnr']:.2f} dB "
              f"(box half-size {r['half_size']:.2f}, {r['seconds']:.0f} s)")
    scores = [r["psnr"] for r in rows]
    print(f"  spread over frames: {max(scores) - min(scores):.2f} dB")


if __name__ == "__main__":
    main()
