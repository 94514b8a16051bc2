"""Issue 3's benchmark: centralised baseline vs robots alone vs Di-NeRF (known / unknown poses).

Same data and the same optimiser steps per model: the baseline trains ``rounds * steps`` steps on
all training views (true poses); each robot trains ``rounds * steps`` steps on its own views,
alone or in the swarm. Every model is scored on the same held-out views of the whole scene
(every 8th view, or --test-every), rendered in the shared frame; "others" are the held-out views that lie outside
the robot's sector (only other robots saw that part of the scene).

    .venv/bin/python benchmarks/bench_consensus.py --data ../shared/data/nerf_synthetic/lego --width 100 \\
        --robots 2 --rounds 80 --steps 25 --modes baseline,alone,known,unknown --init coarse

Prints one table; ``--json FILE`` keeps every figure. Runs in one process (the in-process
simulation runs exactly the daemon's trainer code), threads per ``--threads``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.consensus import ConsensusConfig  # noqa: E402
from agent.data.loaders import load_views  # noqa: E402
from agent.data.split import SplitConfig, split_views  # noqa: E402
from agent.evaluation import EvalSet, evaluate_robot, train_baseline  # noqa: E402
from agent.robust import RobustConfig  # noqa: E402
from agent.swarm import Simulation, SwarmTrainingConfig  # noqa: E402
from agent.trainer import CoarseToFineConfig, DepthConfig, TrainConfig  # noqa: E402
from cli.config import apply_overrides  # noqa: E402
from protocol.membership import Topology  # noqa: E402


def coarse_initial_poses(robots, reference: int, neighbours) -> tuple[dict, dict]:
    """Keyframe summaries + RANSAC Sim(3) between neighbours, composed along the graph."""
    from agent.align import AlignConfig, compose_along_graph, estimate_relative, summarise

    cfg = AlignConfig()
    summaries = {i: summarise(v, cfg=cfg) for i, v in robots.items()}
    estimates, report = {}, {}
    for i in robots:
        for j in neighbours[i]:
            if i < j:
                res = estimate_relative(summaries[i], summaries[j], cfg)
                estimates[(i, j)] = res
                report[f"{i}-{j}"] = {"success": res.success, "inliers": res.inliers, "reason": res.reason}
    poses = compose_along_graph(reference, estimates)
    out = {i: torch.as_tensor(poses[i], dtype=torch.float32) for i in poses}
    sizes = {i: summaries[i].nbytes for i in summaries}
    return out, {"pairs": report, "summary_bytes": sizes}


def score(trainer, evalset: EvalSet, robot_id: int) -> dict:
    e = evaluate_robot(trainer, evalset, robot_id)
    return {k: round(v, 4) for k, v in e.summary().items()}


def _suspected(sim: Simulation) -> dict[int, tuple[int, int, int]]:
    """Per robot, how often robust consensus doubted an (honest) neighbour: with no doubt at all, its
    models are bit for bit those of a run without it."""
    return {i: (c.clipper.clipped_count, c.clipper.erratic_count, c.clipper.uncorrelated_count)
            for i, t in sim.trainers.items() if (c := t.consensus) is not None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="procedural:views=100,width=64")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--robots", type=int, default=2)
    ap.add_argument("--overlap", type=float, default=0.0)
    ap.add_argument("--box-half-size", type=float, default=None,
                    help="the object box's half-size (default: the data's; without alpha it still grows to the cameras)")
    ap.add_argument("--test-every", type=int, default=8, help="every k-th view is held out (a scenario's split.test_every)")
    ap.add_argument("--topology", default="full")
    ap.add_argument("--rounds", type=int, default=80)
    ap.add_argument("--steps", type=int, default=25, help="steps per round (80 x 25 beat 20 x 100 on lego)")
    ap.add_argument("--rho", type=float, default=None, help="rho0 (default: ConsensusConfig's)")
    ap.add_argument("--rho-growth", type=float, default=None)
    ap.add_argument("--modes", default="baseline,alone,known,unknown")
    ap.add_argument("--frame", default="first_camera", help="local frames for 'unknown' (split frame kind)")
    ap.add_argument("--init", default="coarse", choices=["identity", "coarse"], help="initial relative pose")
    ap.add_argument("--pose-mode", default="se3", choices=["se3", "sim3"])
    ap.add_argument("--c2f", action="store_true", help="coarse-to-fine hash levels (BARF-style)")
    ap.add_argument("--depth-prior", default="none", choices=["none", "true", "scaled"])
    ap.add_argument("--depth-weight", type=float, default=0.0)
    ap.add_argument("--robust", choices=["on", "off"], default="on",
                    help="robust consensus (agent.robust; on is the default): off measures what it costs without an attack")
    ap.add_argument("--set", action="append", default=[], help="TrainConfig override, e.g. optim.lr=5e-3")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    modes = args.modes.split(",")

    views = load_views(args.data, width=args.width)
    if args.box_half_size is not None:
        from agent.data.capture import estimate_scene_box

        centre, _, _ = estimate_scene_box(views)
        views.meta["scene_box_world"] = {"center": centre.tolist(), "half_size": args.box_half_size}
    train = apply_overrides(TrainConfig(), args.set)
    consensus = ConsensusConfig(robust=RobustConfig(enabled=args.robust == "on"))
    if args.rho is not None:
        consensus = dataclasses.replace(consensus, rho0=args.rho)
    if args.rho_growth is not None:
        consensus = dataclasses.replace(consensus, rho_growth=args.rho_growth)
    swarm_cfg = SwarmTrainingConfig(rounds=args.rounds, steps_per_round=args.steps, seed=args.seed, own_holdout_every=0,
                                    consensus=consensus, train=train)
    total = swarm_cfg.total_steps
    results: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "total_steps_per_model": total}

    known = split_views(views, SplitConfig(robots=args.robots, overlap=args.overlap, frame="world", seed=args.seed,
                                             test_every=args.test_every))
    ev_known = EvalSet.from_split(known)
    ids = sorted(known.robots)
    topo = Topology.from_spec(args.topology, ids)
    neighbours = {i: topo.neighbours(i) for i in ids}
    print(f"{args.data} at {views.width}x{views.height}: {len(ids)} robots "
          f"({', '.join(f'{i}: {len(known.robots[i].views)} views' for i in ids)}), overlap {known.mean_overlap:.0%}, "
          f"{len(ev_known.views)} held-out views; {total} steps per model", flush=True)

    def log_rounds(name):
        def cb(records):
            d = statistics.fmean(r.disagreement for r in records.values())
            k = next(iter(records.values())).round
            print(f"  [{name}] round {k}/{args.rounds} batch psnr "
                  + " ".join(f"{i}:{r.batch_psnr:.1f}" for i, r in records.items()) + f" disagreement {d:.3f}", flush=True)
        return cb

    if "baseline" in modes:
        t0 = time.time()
        all_train = [i for i in range(len(views)) if i not in set(known.eval_indices)]
        run = train_baseline(views.subset(all_train), dataclasses.replace(train, total_steps=total), test_every=0)
        # Scored on the split's held-out views, in the world (= shared, for frame "world") frame.
        sc = score(run.trainer, ev_known, ids[0])
        results["baseline"] = {"all": sc, "seconds": time.time() - t0,
                               "s_per_step": statistics.median(run.step_seconds)}
        print(f"baseline: PSNR {sc['psnr']:.2f} SSIM {sc['ssim']:.3f} ({time.time() - t0:.0f} s)", flush=True)

    for mode in [m for m in ("alone", "known", "unknown") if m in modes]:
        t0 = time.time()
        split = known
        initial = None
        cfg = swarm_cfg
        nb = neighbours if mode != "alone" else {i: set() for i in ids}
        ev = ev_known
        extra = {}
        if mode == "unknown":
            split = split_views(views, SplitConfig(robots=args.robots, overlap=args.overlap, frame=args.frame,
                                                   seed=args.seed, test_every=args.test_every, depth_prior=args.depth_prior,
                                                   random_max_scale=2.0 if args.pose_mode == "sim3" else 1.0))
            ev = EvalSet.from_split(split)
            tcfg = dataclasses.replace(
                train, pose=dataclasses.replace(train.pose, mode=args.pose_mode),
                coarse_to_fine=CoarseToFineConfig(enabled=args.c2f) if args.c2f else train.coarse_to_fine,
                depth=DepthConfig(weight=args.depth_weight) if args.depth_weight else train.depth)
            cfg = dataclasses.replace(swarm_cfg, train=tcfg)
            robots = {i: r.views for i, r in split.robots.items()}
            if args.init == "coarse":
                initial, extra = coarse_initial_poses(robots, ids[0], neighbours)
                for i, T in initial.items():
                    from agent.geometry import pose_error
                    extra.setdefault("initial_error", {})[i] = pose_error(T.double(), ev.T_shared_from_local(i))
                print(f"coarse alignment: {extra}", flush=True)
        robots = {i: r.views for i, r in split.robots.items()}
        sim = Simulation(robots, nb, split.box_from_shared, cfg, initial_poses=initial)
        sim.run(log_rounds(mode))
        rec = {"seconds": time.time() - t0, "robots": {}, **extra}
        thetas = [list(t.theta().values()) for t in sim.trainers.values()]
        from agent.consensus import disagreement

        rec["disagreement"] = dict(zip(ids, disagreement(thetas)))
        rec["suspected"] = _suspected(sim)
        for i, tr in sim.trainers.items():
            rec["robots"][i] = score(tr, ev, i)
        results[mode] = rec
        print(f"{mode}: " + " | ".join(
            f"robot {i}: all {s['psnr']:.2f}/{s['ssim']:.3f} others {s['psnr_others_only']:.2f}"
            + (f" rot {s['pose_rotation_deg']:.2f} deg t {s['pose_translation']:.4f}" if mode == "unknown" else "")
            for i, s in rec["robots"].items()) + f" ({rec['seconds']:.0f} s)", flush=True)
        if rec["suspected"]:
            print(f"  robust consensus {args.robust}: neighbours' models clipped / erratic / unrelated (a pair a round): "
                  + ", ".join(f"robot {i} {c}/{e}/{u}" for i, (c, e, u) in rec["suspected"].items()), flush=True)

    print("\nsummary (PSNR dB all / others-only; pose error for unknown):")
    base = results.get("baseline", {}).get("all", {}).get("psnr")
    for mode in ("alone", "known", "unknown"):
        if mode not in results:
            continue
        for i, s in results[mode]["robots"].items():
            line = f"  {mode:8s} robot {i}: {s['psnr']:.2f} / {s['psnr_others_only']:.2f}"
            if base is not None:
                line += f"  (baseline {base:.2f}, diff {s['psnr'] - base:+.2f})"
            if "alone" in results and mode != "alone":
                line += f"  others vs alone {s['psnr_others_only'] - results['alone']['robots'][i]['psnr_others_only']:+.2f}"
            if mode == "unknown":
                line += f"  rot {s['pose_rotation_deg']:.3f} deg, t {s['pose_translation']:.4f}"
            print(line)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
