"""Online mapping in a swarm: robots that explore (views arriving round by round) against the same robots
given all their views at start, and against each robot exploring alone (issue 44's comparison).

    flock /tmp/dinerf-heavy.lock nice python benchmarks/bench_online.py [--rounds 8 --steps 50]

The procedural room on a 360 deg orbit, split by sector between the robots (``split``, world frame:
poses known, so alignment is not what is measured here). Each robot's camera moves along its own
sector in capture order, its training views arriving evenly over the rounds: robot 1 from 0 deg and
robot 2 from 180 deg, so each reaches the other's first places only at the end of the run. Every
mode trains the same rounds x steps on the same seed (in one process, :class:`agent.swarm.Simulation`,
C-ADMM through memory) and is scored after every round on the split's held-out views: all of them
and those only the other robots saw. Printed per mode and robot: PSNR after each round, the final
PSNR, and the first round within 1 dB of it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from agent.data.ros.intake import Keyframe  # noqa: E402
from agent.data.split import SplitConfig, split_views  # noqa: E402
from agent.data.stream import StreamConfig, ViewStream  # noqa: E402
from agent.data.views import Views  # noqa: E402
from agent.defaults import Capture  # noqa: E402
from agent.evaluation import EvalSet, evaluate_robot  # noqa: E402
from agent.swarm import Simulation, SwarmTrainingConfig  # noqa: E402
from benchmarks.bench_stream import _NoIntake  # noqa: E402
from cli.options import load_train_config  # noqa: E402
from protocol.membership import Topology  # noqa: E402


def keyframes(views: Views) -> list[Keyframe]:
    return [Keyframe(views.names[i], views.images[i].numpy(), views.c2w[i].double().numpy(),
                     tuple(float(x) for x in views.intrinsics[i]), i, time.time_ns()) for i in range(len(views))]


def run_mode(mode: str, split, cfg: SwarmTrainingConfig, neighbours, evalset: EvalSet, folder: Path) -> dict:
    """One swarm (or each robot alone) -> per robot, PSNR (all, others-only) after every round."""
    ids = sorted(split.robots)
    arrivals = {i: keyframes(split.robots[i].views) for i in ids}
    per_round = {i: -(-len(arrivals[i]) // cfg.rounds) for i in ids}
    streams, first = {}, {}
    if mode == "offline":
        first = {i: split.robots[i].views for i in ids}
    else:
        for i in ids:
            streams[i] = ViewStream(StreamConfig(), _NoIntake(), folder / f"{mode}{i}", None, 0, len(arrivals[i]))
            streams[i]._admit(arrivals[i][:per_round[i]])
            first[i] = streams[i].initial_views()
    nb = neighbours if mode != "alone" else {i: set() for i in ids}
    t0 = time.monotonic()
    sim = Simulation(first, nb, split.box_from_shared, cfg, streams=streams)
    curves = {i: [] for i in ids}
    for k in range(cfg.rounds):
        for i, stream in streams.items():
            if k:
                stream._admit(arrivals[i][k * per_round[i]:(k + 1) * per_round[i]])
        sim.run_round()
        for i, trainer in sim.trainers.items():
            s = evaluate_robot(trainer, evalset, i, with_ssim=False).summary()
            curves[i].append((s["psnr"], s["psnr_others_only"]))
        print(f"  [{mode}] round {k + 1}/{cfg.rounds} " + "  ".join(
            f"robot {i}: {len(streams[i]._rows) if streams else len(first[i])} views, PSNR {c[-1][0]:.2f} / "
            f"others {c[-1][1]:.2f}" for i, c in curves.items()), flush=True)
    return {"curves": curves, "seconds": time.monotonic() - t0}


def within_1db(curve: list[float]) -> int:
    """The first round (1-based) from which the PSNR stays within 1 dB of the final one."""
    final = curve[-1]
    k = len(curve)
    while k > 1 and curve[k - 2] >= final - 1.0:
        k -= 1
    return k


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="procedural:views=64,width=48,room=1")
    ap.add_argument("--robots", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--modes", default="offline,online,alone")
    ap.add_argument("--set", action="append", default=[], help="a [training.train] setting, e.g. optim.lr=5e-3")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    from agent.data.loaders import load_views

    views = load_views(a.data)
    split = split_views(views, SplitConfig(robots=a.robots, overlap=0.0, frame="world", test_every=8))
    evalset = EvalSet.from_split(split)
    ids = sorted(split.robots)
    topo = Topology.from_spec("full", ids)
    neighbours = {i: topo.neighbours(i) for i in ids}
    train = load_train_config(None, a.set, a.rounds * a.steps,
                              capture=Capture(unbounded=views.shows_surroundings, width=views.width))
    cfg = SwarmTrainingConfig(rounds=a.rounds, steps_per_round=a.steps, own_holdout_every=0, train=train)
    print(f"{a.data}: {len(ids)} robots ({', '.join(f'{i}: {len(split.robots[i].views)} views' for i in ids)}), "
          f"{len(evalset.views)} held out, {a.rounds} rounds x {a.steps} steps", flush=True)
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-online-") as tmp:
        for mode in a.modes.split(","):
            results[mode] = run_mode(mode, split, cfg, neighbours, evalset, Path(tmp))
    print("\nPSNR after the last round, all / others-only (first round within 1 dB of the final, all / others):")
    for mode, r in results.items():
        for i, c in r["curves"].items():
            alls, others = [x for x, _ in c], [y for _, y in c]
            print(f"  {mode:8s} robot {i}: {alls[-1]:5.2f} / {others[-1]:5.2f}  (rounds {within_1db(alls)} / "
                  f"{within_1db(others)})  curve " + " ".join(f"{x:.1f}" for x in alls) + f"  ({r['seconds']:.0f} s)")
    if "online" in results and "offline" in results:
        gaps = [results["online"]["curves"][i][-1][0] - results["offline"]["curves"][i][-1][0] for i in ids]
        print(f"online - offline, all views: {' '.join(f'{g:+.2f}' for g in gaps)} dB (mean {statistics.fmean(gaps):+.2f})")
    if "online" in results and "alone" in results:
        gaps = [results["online"]["curves"][i][-1][1] - results["alone"]["curves"][i][-1][1] for i in ids]
        print(f"online swarm - online alone, others-only views: {' '.join(f'{g:+.2f}' for g in gaps)} dB")


if __name__ == "__main__":
    main()
