"""Issue 21's benchmark: float32 snapshots against each compression mode, on the same data and steps.

Every mode runs the in-process simulation with :class:`agent.swarm.ProtocolWire`, the daemons'
own encode, decode and base resolution, so a robot trains on exactly what its neighbours would
receive over Zenoh (the loopback test checks the daemons against it bit for bit). Every model is
scored on the same held-out views of the whole scene; "others" are those only other robots saw.
Bytes are the push sizes on the wire (header included), per link per round; the ratio is to the
raw float32 snapshot; the seconds are what one push takes on a link of ``--rate-mbit``.

    nice .venv/bin/python benchmarks/bench_compression.py                        # procedural scene
    nice .venv/bin/python benchmarks/bench_compression.py --data ../shared/data/nerf_synthetic/lego \\
        --width 100 --robots 5 --topology ring --rounds 80 --steps 25 --field-log2 17    # the issue's setting

``--frame first_camera`` gives each robot its own frame: poses start from the coarse alignment
and are learnt (the paper's unknown-pose setting); the worst pose error is printed per mode.

``--json FILE`` keeps every figure.
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
sys.path.insert(0, str(REPO / "benchmarks"))

from agent.consensus import ConsensusConfig  # noqa: E402
from agent.data.loaders import load_views  # noqa: E402
from agent.data.split import SplitConfig, split_views  # noqa: E402
from agent.evaluation import EvalSet, evaluate_robot  # noqa: E402
from agent.swarm import ProtocolWire, Simulation, SwarmTrainingConfig  # noqa: E402
from agent.trainer import TrainConfig  # noqa: E402
from cli.config import apply_overrides  # noqa: E402
from protocol.compression import MODES, CompressionConfig  # noqa: E402
from protocol.membership import Topology  # noqa: E402
from bench_consensus import coarse_initial_poses  # noqa: E402  (benchmarks/, on the path above)


FLAGS = ("exact", "anchor_exact", "robust_off")


def mode_config(mode: str, topk: float) -> tuple[CompressionConfig, bool, bool, bool]:
    """``MODE[@key=value,...]``: a mode with CompressionConfig fields set, e.g.
    ``delta+ternary@ternary_threshold=1.0``; ``@exact`` runs C-ADMM on each robot's exact theta
    rather than on the copy its neighbours hold (the public copy, as the daemons do);
    ``@anchor_exact`` keeps the duals on the public copy but fixes the round's anchors from the
    robot's exact theta_i^k; ``@robust_off`` takes every neighbour's model as it comes (robust
    consensus off: the code before issue 43, the baseline of its no-attack cost)."""
    name, _, rest = mode.partition("@")
    fields: dict = {"compression": name, "topk_fraction": topk}
    items = [item for item in rest.split(",") if item]
    for item in items:
        if item not in FLAGS:
            key, _, value = item.partition("=")
            fields[key] = type(getattr(CompressionConfig(), key))(value)
    return CompressionConfig(**fields), "exact" not in items, "anchor_exact" in items, "robust_off" not in items


def run_mode(mode: str, split, neighbours, cfg: SwarmTrainingConfig, topk: float, ev: EvalSet,
             initial: dict | None = None) -> dict:
    """Train the swarm with snapshots in ``mode``; scores per robot and bytes per push."""
    t0 = time.time()
    robots = {i: r.views for i, r in split.robots.items()}
    compression, on_public, anchor_on_exact, robust = mode_config(mode, topk)
    consensus = dataclasses.replace(cfg.consensus, robust=dataclasses.replace(cfg.consensus.robust, enabled=robust))
    sim = Simulation(robots, neighbours, split.box_from_shared, dataclasses.replace(cfg, consensus=consensus),
                     initial_poses=initial)
    sim.on_public, sim.anchor_on_exact = on_public, anchor_on_exact
    sim.wire = ProtocolWire(compression, next(iter(sim.thetas.values())), sorted(robots))
    sim.run()
    raw = sim.wire.spec.float32_bytes
    pushes = [b for sizes in sim.wire.sent.values() for b in sizes]
    scores = {i: evaluate_robot(t, ev, i).summary() for i, t in sim.trainers.items()}
    return {
        "psnr": statistics.fmean(s["psnr"] for s in scores.values()),
        "psnr_others": statistics.fmean(s["psnr_others_only"] for s in scores.values()),
        "robots": {i: {k: s[k] for k in ("psnr", "psnr_others_only", "pose_rotation_deg", "pose_translation")}
                   for i, s in scores.items()},
        "worst_rotation_deg": max(s["pose_rotation_deg"] for s in scores.values()),
        "worst_translation": max(s["pose_translation"] for s in scores.values()),
        "bytes_per_link_round": statistics.fmean(pushes), "raw_float32_bytes": raw,
        "ratio": statistics.fmean(pushes) / raw, "seconds": time.time() - t0,
        "clipped": sum(t.consensus.clipper.clipped_count for t in sim.trainers.values()),
        "erratic": sum(t.consensus.clipper.erratic_count for t in sim.trainers.values()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="procedural:views=60,width=48")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--overlap", type=float, default=0.2)
    ap.add_argument("--topology", default="ring")
    ap.add_argument("--frame", default="world",
                    help="robots' local frames: world (known poses) or a split frame kind such as first_camera "
                         "(unknown poses: coarse alignment, then se3 poses learnt as in bench_consensus)")
    ap.add_argument("--rounds", type=int, default=16)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--field-log2", type=int, default=14, help="log2 hash-table size per level")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--topk-fraction", type=float, default=0.05)
    ap.add_argument("--long-rounds", type=int, default=0,
                    help="also run float32 with this many (longer) rounds at the same total steps (0 = not)")
    ap.add_argument("--rate-mbit", type=float, default=20.0, help="link rate the push times are quoted at")
    ap.add_argument("--set", action="append", default=[], help="TrainConfig override, e.g. rays_per_step=512")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rho", type=float, default=None, help="rho0 (default: ConsensusConfig's)")
    ap.add_argument("--test-every", type=int, default=SplitConfig().test_every, help="every k-th view is held out (a scenario's split.test_every)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    views = load_views(args.data, width=args.width)
    train = apply_overrides(TrainConfig(), [f"field.grid.log2_hashmap_size={args.field_log2}", *args.set])
    consensus = ConsensusConfig() if args.rho is None else ConsensusConfig(rho0=args.rho)
    cfg = SwarmTrainingConfig(rounds=args.rounds, steps_per_round=args.steps, seed=args.seed, own_holdout_every=0,
                              consensus=consensus, train=train)
    split = split_views(views, SplitConfig(robots=args.robots, overlap=args.overlap, frame=args.frame, seed=args.seed,
                                           test_every=args.test_every))
    ev = EvalSet.from_split(split)
    ids = sorted(split.robots)
    topo = Topology.from_spec(args.topology, ids)
    neighbours = {i: topo.neighbours(i) for i in ids}
    initial = None
    if args.frame != "world":
        initial, report = coarse_initial_poses({i: r.views for i, r in split.robots.items()}, ids[0], neighbours)
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(train, pose=dataclasses.replace(train.pose, mode="se3")))
        print(f"coarse alignment: {report['pairs']}", flush=True)
    print(f"{args.data} at {views.width}x{views.height}: {len(ids)} robots on a {args.topology}, {args.rounds} rounds x "
          f"{args.steps} steps, log2 table {args.field_log2}; {len(ev.views)} held-out views", flush=True)
    results: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "modes": {}}
    for mode in args.modes.split(","):
        r = results["modes"][mode] = run_mode(mode, split, neighbours, cfg, args.topk_fraction, ev, initial)
        _print_mode(mode, r)
    if args.long_rounds:
        total = args.rounds * args.steps
        if total % args.long_rounds:
            raise SystemExit(f"--long-rounds {args.long_rounds} does not divide {total} steps")
        long_cfg = dataclasses.replace(cfg, rounds=args.long_rounds, steps_per_round=total // args.long_rounds)
        name = f"none@{args.long_rounds}x{total // args.long_rounds}"
        r = results["modes"][name] = run_mode("none", split, neighbours, long_cfg, args.topk_fraction, ev, initial)
        r["pushes_per_link"] = args.long_rounds
        _print_mode(name, r)
    _print_summary(results, args)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")


def _print_mode(mode: str, r: dict) -> None:
    print(f"  {mode:10s} PSNR {r['psnr']:.2f} dB, others-only {r['psnr_others']:.2f} dB | "
          f"{r['bytes_per_link_round'] / 1e6:.4f} MB per link per round, ratio {r['ratio']:.4f} "
          f"({r['seconds']:.0f} s), worst pose {r['worst_rotation_deg']:.3f} deg / {r['worst_translation']:.4f}, "
          f"neighbours clipped {r['clipped']} times, erratic {r['erratic']} times",
          flush=True)


def _print_summary(results: dict, args) -> None:
    """PSNR against float32, bytes per push and per whole run (a run of fewer rounds pushes less often)."""
    ref = results["modes"].get("none")
    print(f"\nsummary (PSNR all / others-only, difference to float32; bytes per link per round; "
          f"one push at {args.rate_mbit:g} Mbit/s; MB per link over the run):")
    for mode, r in results["modes"].items():
        diff = f" ({r['psnr'] - ref['psnr']:+.2f} / {r['psnr_others'] - ref['psnr_others']:+.2f})" if ref else ""
        push_s = r["bytes_per_link_round"] * 8 / (args.rate_mbit * 1e6)
        print(f"  {mode:10s} {r['psnr']:6.2f} / {r['psnr_others']:6.2f} dB{diff}  {r['bytes_per_link_round']:>11,.0f} B"
              f"  1/{1 / r['ratio']:6.1f} of float32  {push_s:7.3f} s"
              f"  {r['bytes_per_link_round'] * r.get('pushes_per_link', args.rounds) / 1e6:9.1f} MB"
              + (f"  pose {r['worst_rotation_deg']:.3f} deg / {r['worst_translation']:.4f}" if args.frame != "world" else ""))


if __name__ == "__main__":
    main()
