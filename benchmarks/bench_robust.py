"""Issue 43's benchmark: one hostile robot against the swarm, and what robust consensus costs without one.

**Poison** (``--part poison``, the in-process simulation, which runs exactly the daemon's trainer
code): one robot trains as usual but sends, as its own model, from ``--attack-from`` on:
``huge`` (every value 1e30), ``minus_ten`` (-10 theta), ``replay`` (its round-1 model, every
round), ``noise`` (Gaussian noise of each tensor's RMS). The baseline is the same swarm with that
robot ``silent`` from the round its attack would begin (until then, it is the same robot in every
run; ``absent``: nobody ever hears it); ``clean`` is the swarm without any attack. Figures: the honest
robots' mean PSNR on the held-out views (all / others-only), its difference to the silent run,
the round at which every honest neighbour of the hostile robot named it, and how often an honest
neighbour was clipped or found erratic. ``--robust both`` also runs every attack with robust consensus off.

**Round steering and a NaN-only neighbour** (``--part daemons``): real ``dinerf-agent up``
processes on loopback; the hostile one is the real daemon with one change
(``tests/system/hostile.py``): ``future`` heartbeats the swarm's last round and answers every
``latest`` query with a forged model of that round; ``nan`` pushes NaN snapshots while heartbeating.
The baseline is the same swarm with that robot ``silent`` (it trains, so the CPU is shared as
in the attacks, but sends nothing and holds its token); ``mute`` (tests/system/mute.py) holds
only a token. Figures: rounds trained per honest robot, early ``done.json``, seconds per round,
honest PSNR against the silent run.

    nice .venv/bin/python benchmarks/bench_robust.py --part poison --robots 3 --topology full
    nice .venv/bin/python benchmarks/bench_robust.py --part poison --robots 5 --topology ring
    nice .venv/bin/python benchmarks/bench_robust.py --part daemons --robots 3 --topology full

Prints one table per part; ``--json FILE`` keeps every figure.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.consensus import ConsensusConfig  # noqa: E402
from agent.data.loaders import load_views  # noqa: E402
from agent.data.split import SplitConfig, split_views  # noqa: E402
from agent.evaluation import EvalSet, evaluate_robot  # noqa: E402
from agent.robust import RobustConfig  # noqa: E402
from agent.swarm import ProtocolWire, Simulation, SwarmTrainingConfig  # noqa: E402
from agent.trainer import TrainConfig  # noqa: E402
from cli.config import apply_overrides  # noqa: E402
from protocol.compression import CompressionConfig  # noqa: E402
from protocol.membership import Topology  # noqa: E402

# The quickstart's field and schedule (scenarios/quickstart): small enough for many runs on 2 cores.
QUICKSTART = ["rays_per_step=1024", "field.density_hidden=32", "field.color_hidden=32",
              "field.grid.log2_hashmap_size=14", "field.grid.num_levels=12", "field.grid.max_resolution=256",
              "occupancy.resolution=48", "occupancy.warmup_steps=64", "occupancy.update_every=16"]

Tensors = dict[str, torch.Tensor]


def _attack(kind: str, seed: int) -> Callable[[int, Tensors], Tensors]:
    """What the hostile robot's neighbours receive instead of its model of round k."""
    g = torch.Generator().manual_seed(seed + 7919)  # not the init_seed's stream: its draws would echo theta^0
    first: list[Tensors] = []

    def forge(k: int, theta: Tensors) -> Tensors:
        if not first:
            first.append({n: t.clone() for n, t in theta.items()})
        if kind == "huge":
            return {n: torch.full_like(t, 1e30) for n, t in theta.items()}
        if kind == "minus_ten":
            return {n: -10 * t for n, t in theta.items()}
        if kind == "replay":
            return {n: t.clone() for n, t in first[0].items()}
        if kind == "noise":
            return {n: torch.randn(t.shape, generator=g) * t.pow(2).mean().sqrt() for n, t in theta.items()}
        raise ValueError(kind)
    return forge


def hostile_forge(hostile: int, attack: Callable[[int, Tensors], Tensors], attack_from: int):
    """``Simulation.forge``: one sender's models replaced, from a round on, in what its neighbours
    receive (it anchors its own consensus on its real model, as the real daemon with one hostile
    change does)."""
    def forge(sender: int, round_index: int, theta: Tensors) -> Tensors | None:
        return attack(round_index, theta) if sender == hostile and round_index >= attack_from else None
    return forge


def run_poison(attack: str, robust: bool, split, neighbours, cfg: SwarmTrainingConfig, ev: EvalSet, hostile: int,
               attack_from: int, seed: int) -> dict:
    t0 = time.time()
    ids = sorted(split.robots)
    if attack == "absent":  # nobody hears the hostile robot, and it hears nobody
        neighbours = {i: set(nb) - {hostile} if i != hostile else set() for i, nb in neighbours.items()}
    robust_cfg = dataclasses.replace(cfg.consensus.robust, enabled=robust)
    cfg = dataclasses.replace(cfg, consensus=dataclasses.replace(cfg.consensus, robust=robust_cfg))
    sim = Simulation({i: r.views for i, r in split.robots.items()}, neighbours, split.box_from_shared, cfg)
    sim.wire = ProtocolWire(CompressionConfig(), next(iter(sim.thetas.values())), ids)
    if attack == "silent":
        sim.silent_from = {hostile: attack_from}
    elif attack not in ("absent", "clean"):
        sim.forge = hostile_forge(hostile, _attack(attack, seed), attack_from)
    named: dict[int, int] = {}  # honest neighbour -> the round it first named the hostile robot
    false_clips = 0

    def on_round(records) -> None:
        nonlocal false_clips
        k = next(iter(records.values())).round
        for i, robot in sim.robots.items():
            c = robot.trainer.consensus
            if i == hostile or c is None:
                continue
            if any(n.neighbour == hostile for n in c.news) and i not in named:
                named[i] = k
            false_clips += sum(1 for j, f in c.clipper.factors.items() if j != hostile and f < 1)
            false_clips += sum(1 for j, why in c.clipper.reason.items() if j != hostile and why == "erratic"
                               and c.clipper.factors.get(j, 1.0) >= 1)

    sim.run(on_round)
    honest = [i for i in ids if i != hostile]
    scores = {i: evaluate_robot(sim.trainers[i], ev, i).summary() for i in honest}
    hostile_nb = sorted(j for j in honest if hostile in neighbours[j]) if attack not in ("silent", "absent", "clean") else []
    return {
        "attack": attack, "robust": robust,
        "psnr": statistics.fmean(s["psnr"] for s in scores.values()),
        "psnr_others": statistics.fmean(s["psnr_others_only"] for s in scores.values()),
        "robots": {i: {"psnr": s["psnr"], "psnr_others_only": s["psnr_others_only"]} for i, s in scores.items()},
        "named_by": named, "named_round": max(named.values()) if hostile_nb and set(named) >= set(hostile_nb) else None,
        "honest_clips": false_clips, "seconds": time.time() - t0, "honest_models": _digest(sim, honest),
    }


def _digest(sim: Simulation, robots: list[int]) -> str:
    """A hash of the honest robots' final models: equal hashes, bit-identical models."""
    h = hashlib.sha256()
    for i in robots:
        for name, t in sorted(sim.trainers[i].theta().items()):
            h.update(name.encode() + t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def part_poison(args) -> dict:
    views = load_views(args.data, width=args.width)
    train = apply_overrides(TrainConfig(), [*QUICKSTART, *args.set])
    cfg = SwarmTrainingConfig(rounds=args.rounds, steps_per_round=args.steps, seed=args.seed, own_holdout_every=0,
                              consensus=ConsensusConfig(rho0=args.rho, robust=RobustConfig()), train=train)
    split = split_views(views, SplitConfig(robots=args.robots, overlap=args.overlap, frame="world", seed=args.seed,
                                           test_every=args.test_every))
    ev = EvalSet.from_split(split)
    ids = sorted(split.robots)
    topo = Topology.from_spec(args.topology, ids)
    neighbours = {i: set(topo.neighbours(i)) for i in ids}
    hostile = args.hostile if args.hostile is not None else ids[-1]
    print(f"{args.data}: {len(ids)} robots on a {args.topology}, robot {hostile} hostile from round "
          f"{args.attack_from}; {args.rounds} rounds x {args.steps} steps, rho {args.rho}; "
          f"{len(ev.views)} held-out views", flush=True)
    runs = []
    for attack in args.attacks.split(","):
        for robust in ((True, False) if args.robust == "both" and attack not in ("silent", "absent", "clean")
                       else (args.robust != "off",)):
            r = run_poison(attack, robust, split, neighbours, cfg, ev, hostile, args.attack_from, args.seed)
            runs.append(r)
            print(f"  {attack:10s} robust {'on ' if robust else 'off'}: honest PSNR {r['psnr']:.2f} / others-only "
                  f"{r['psnr_others']:.2f} dB, named at round {r['named_round']} {r['named_by']}, honest neighbours suspected "
                  f"{r['honest_clips']} ({r['seconds']:.0f} s)", flush=True)
    silent = next((r for r in runs if r["attack"] == "silent"), None)
    print("\nsummary (honest robots' mean PSNR, all / others-only; difference to the silent-robot run):")
    for r in runs:
        diff = "" if silent is None else (f"  {r['psnr'] - silent['psnr']:+.2f} / "
                                          f"{r['psnr_others'] - silent['psnr_others']:+.2f} dB vs silent")
        same = "" if silent is None or r is silent else (", honest models bit-identical to silent's"
                                                          if r["honest_models"] == silent["honest_models"] else "")
        print(f"  {r['attack']:10s} robust {'on ' if r['robust'] else 'off'} {r['psnr']:.2f} / {r['psnr_others']:.2f}"
              f"{diff}  named at round {r['named_round']}, honest suspected {r['honest_clips']}{same}")
    return {"runs": runs}


def _daemon_training(args) -> dict:
    """The quickstart's training section (scenarios/quickstart), as the swarm file holds it."""
    return {"rounds": args.rounds, "steps_per_round": args.steps, "seed": args.seed, "own_holdout_every": 0,
            "consensus": {"rho0": args.rho},
            "train": {"rays_per_step": 1024, "field": {"density_hidden": 32, "color_hidden": 32,
                                                       "grid": {"log2_hashmap_size": 14, "num_levels": 12,
                                                                "max_resolution": 256}},
                      "occupancy": {"resolution": 48, "warmup_steps": 64, "update_every": 16}}}


def run_daemons(attack: str, args, tmp: Path, ev: EvalSet) -> dict:
    """One real swarm with its highest robot ``mute`` or hostile (tests/system/hostile.py)."""
    import subprocess

    from agent.checkpoint import load_for_eval
    from tests.system.harness import make_swarm

    views, width = _procedural_size(args.data)
    swarm = make_swarm(tmp / attack.replace("+", "_"), robots=args.robots, topology=args.topology,
                       training=_daemon_training(args), daemon={"round_timeout_s": args.round_timeout, "eval_every": 0},
                       views=views, width=width, overlap=args.overlap, seed=args.seed, secure=True)
    hostile = max(swarm.robots)
    honest = [i for i in swarm.robots if i != hostile]
    mute = None
    t0 = time.monotonic()
    try:
        if attack == "mute":
            mute = subprocess.Popen([sys.executable, str(REPO / "tests/system/mute.py"), str(swarm.swarm_file),
                                     str(hostile), "3600"], cwd=REPO, stdout=subprocess.PIPE, text=True)
            assert mute.stdout.readline().strip() == "ready"
        for i in honest:
            swarm.start(i)
        if attack != "mute":
            swarm.start(hostile, hostile=attack)
        swarm.wait_all(honest, timeout=args.daemon_timeout)
    finally:
        wall = time.monotonic() - t0
        if mute is not None:
            mute.kill()
        swarm.stop()
    per_robot = {}
    for i in honest:
        tel, done = swarm.telemetry(i), swarm.done(i)
        named = [t.round for t in tel if hostile in t.suspects]
        trainer = load_for_eval(swarm.run_dir(i), swarm.root / f"robot{i}")
        s = evaluate_robot(trainer, ev, i).summary()
        per_robot[i] = {"psnr": s["psnr"], "psnr_others_only": s["psnr_others_only"],
                        "rounds_trained": sum(1 for t in tel if t.steps == args.steps), "done": done,
                        "round_s": statistics.fmean(b.monotonic - a.monotonic for a, b in zip(tel, tel[1:])),
                        "max_wait_s": max(t.seconds_wait for t in tel), "named_round": named[0] if named else None,
                        "suspects": tel[-1].suspects}
    return {"attack": attack, "wall_s": wall, "robots": per_robot,
            "psnr": statistics.fmean(r["psnr"] for r in per_robot.values()),
            "psnr_others": statistics.fmean(r["psnr_others_only"] for r in per_robot.values()),
            "round_s": statistics.fmean(r["round_s"] for r in per_robot.values())}


def _procedural_size(data: str) -> tuple[int, int]:
    """views and width of a ``procedural:views=V,width=W`` source (the daemons' harness makes its own)."""
    fields = dict(item.split("=") for item in data.partition(":")[2].split(",") if "=" in item)
    if not data.startswith("procedural:") or set(fields) - {"views", "width"}:
        raise SystemExit("--part daemons runs on the procedural scene: --data procedural:views=V,width=W")
    return int(fields.get("views", 60)), int(fields.get("width", 48))


def part_daemons(args) -> dict:
    import tempfile

    views, width = _procedural_size(args.data)
    split = split_views(load_views(f"procedural:views={views},width={width}"),
                        SplitConfig(robots=args.robots, overlap=args.overlap, frame="world", seed=args.seed))
    ev = EvalSet.from_split(split)  # the harness splits exactly so
    print(f"{args.data}: {args.robots} real robots on a {args.topology}, the highest one mute or hostile; "
          f"{args.rounds} rounds x {args.steps} steps, round timeout {args.round_timeout} s; "
          f"{len(ev.views)} held-out views", flush=True)
    runs = []
    with tempfile.TemporaryDirectory(prefix="bench-robust-") as tmp:
        for attack in args.daemon_attacks.split(","):
            r = run_daemons(attack, args, Path(tmp), ev)
            runs.append(r)
            print(f"  {attack:10s} honest PSNR {r['psnr']:.2f} / {r['psnr_others']:.2f} dB, round {r['round_s']:.2f} s, "
                  f"wall {r['wall_s']:.0f} s; " + "; ".join(
                      f"robot {i}: {x['rounds_trained']} rounds trained, done {x['done'] and x['done']['rounds']} "
                      f"moves {x['done'] and x['done'].get('moves')}, max wait {x['max_wait_s']:.1f} s, named at "
                      f"round {x['named_round']} {x['suspects']}" for i, x in r["robots"].items()), flush=True)
    base = next((r for r in runs if r["attack"] == "silent"), None)
    print("\nsummary (honest robots' mean PSNR all / others-only; against the silent-robot run; round time):")
    for r in runs:
        vs = "" if base is None else (f"  {r['psnr'] - base['psnr']:+.2f} / {r['psnr_others'] - base['psnr_others']:+.2f}"
                                      f" dB, rounds {r['round_s'] / base['round_s']:.2f}x the silent run's")
        print(f"  {r['attack']:10s} {r['psnr']:.2f} / {r['psnr_others']:.2f} dB, {r['round_s']:.2f} s a round{vs}")
    return {"runs": runs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=["poison", "daemons"], default="poison")
    ap.add_argument("--data", default="procedural:views=60,width=48")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--topology", default="full")
    ap.add_argument("--overlap", type=float, default=0.1)
    ap.add_argument("--test-every", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=24)
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--rho", type=float, default=3e-6, help="rho0 (the quickstart's)")
    ap.add_argument("--attacks", default="clean,silent,huge,minus_ten,replay,noise")
    ap.add_argument("--attack-from", type=int, default=1, help="the first round whose model is forged")
    ap.add_argument("--hostile", type=int, default=None, help="the hostile robot (default: the highest id)")
    ap.add_argument("--robust", choices=["on", "off", "both"], default="on")
    ap.add_argument("--daemon-attacks", default="silent,future,nan", help="--part daemons: mute, or hostile.py attacks")
    ap.add_argument("--round-timeout", type=float, default=20.0, help="--part daemons: daemon.round_timeout_s")
    ap.add_argument("--daemon-timeout", type=float, default=1800.0, help="--part daemons: give up on a run after this")
    ap.add_argument("--set", action="append", default=[], help="TrainConfig override, e.g. rays_per_step=512")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    results = {"args": {k: str(v) for k, v in vars(args).items()}}
    if args.part == "poison":
        results["poison"] = part_poison(args)
    else:
        results["daemons"] = part_daemons(args)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
