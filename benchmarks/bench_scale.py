"""Scale of the protocol: N real `dinerf-agent up` robots on one machine, on a ring and on a random
geometric graph, with a tiny field so that the protocol, not the NeRF, is what is measured.

    nice .venv/bin/python benchmarks/bench_scale.py [--robots 32] [--topology ring|rgg|both] \\
        [--rounds 6] [--steps 4] [--out DIR] [--insecure] [--seed 1]

Each robot is a separate process (tests/system/harness.py: a procedural scene split into robot
folders, a swarm.toml, mutual TLS unless --insecure, OMP_NUM_THREADS=1, daemon.threads = 1).
The random geometric graph puts robots at seeded random points of the unit square and joins two
when closer than a radius: the radius of mean degree 4 (2N edges), at the first seed from --seed
on that makes the graph connected; it is written to the swarm file as topology kind "edges".

Per robot, over its rounds after the first (the first includes start-up): the round's wall time
(between consecutive telemetry lines) minus its compute (``seconds_compute``: the training steps)
is the overhead: the barrier (``seconds_wait``, also listed), the C-ADMM dual update, the
checkpoint and the telemetry ("rest": overhead minus wait). Peak RSS per robot is the kernel's
ru_maxrss of the child (wait4). RSS counts shared libraries (torch) in full in every process, so
the swarm's total is the peak of the summed PSS (/proc/<pid>/smaps_rollup: shared pages split
among their users), sampled every 0.5 s. Every robot must exit 0 with telemetry for rounds 1..R;
"short" counts rounds in which a robot heard fewer neighbours than its topology gives it.
CPU per robot-round: the process's CPU time (all threads) of the round and, of it, that of the
training steps (``cpu_seconds``, ``cpu_seconds_compute``); the rest is what the protocol costs the
robot, whatever the scheduler did: on a machine with fewer cores than robots the overhead is about
that CPU times robots per core.
"Robots computing at once" is all robots' compute time over the span of rounds 2..R (one clock:
CLOCK_MONOTONIC is the host's): near or above the cores this swarm gets, it is CPU-bound, and
the barrier waits for neighbours that the scheduler has not run yet.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shutil
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from protocol.membership import Topology, TopologyConfig  # noqa: E402
from tests.system.harness import make_swarm  # noqa: E402


def tiny_training(rounds: int, steps: int) -> dict:
    """A field of ~9k parameters (a ~37 kB snapshot): 4 levels of a 2^10 table, 16-wide MLPs, 64 rays per step."""
    return {"rounds": rounds, "steps_per_round": steps,
            "train": {"rays_per_step": 64,
                      "field": {"grid": {"log2_hashmap_size": 10, "num_levels": 4, "max_resolution": 32},
                                "density_hidden": 16, "color_hidden": 16},
                      "occupancy": {"resolution": 16, "warmup_steps": 4, "update_every": 4}}}


def rgg_edges(n: int, seed: int, degree: float = 4.0) -> tuple[list[list[int]], float, int]:
    """Edges of a connected random geometric graph over ids 1..n with mean ``degree``; the radius and
    the seed used (the first from ``seed`` whose graph at that radius is connected)."""
    want = min(int(round(degree * n / 2)), n * (n - 1) // 2)
    for s in range(seed, seed + 1000):
        rng = random.Random(s)
        pts = {i: (rng.random(), rng.random()) for i in range(1, n + 1)}
        pairs = sorted((math.dist(pts[a], pts[b]), a, b) for a in pts for b in pts if a < b)
        radius = pairs[want - 1][0]
        edges = [[a, b] for d, a, b in pairs if d <= radius]
        if Topology.from_spec("edges", list(pts), edges).is_connected():
            return sorted(edges), radius, s
    raise RuntimeError(f"no connected random geometric graph of mean degree {degree} for {n} robots")


def pss_kb(pid: int) -> int:
    """Proportional set size of a live process in kB (shared pages split among their users; 0 once gone)."""
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def wait_robots(procs: dict, timeout: float) -> tuple[dict[int, int], dict[int, int], int]:
    """Reap every robot with wait4: exit codes, peak RSS per robot (kB) and the peak of the summed PSS (kB)."""
    codes: dict[int, int] = {}
    peak: dict[int, int] = {}
    total = 0
    deadline = time.monotonic() + timeout
    while len(codes) < len(procs) and time.monotonic() < deadline:
        total = max(total, sum(pss_kb(p.pid) for i, p in procs.items() if i not in codes))
        for i, p in procs.items():
            if i in codes:
                continue
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                codes[i] = p.returncode = os.waitstatus_to_exitcode(status)
                peak[i] = usage.ru_maxrss
        time.sleep(0.5)
    return codes, peak, total


def pct(xs: list[float], q: float) -> float:
    """The q-quantile by linear interpolation (q in [0, 1])."""
    xs = sorted(xs)
    if not xs:
        return float("nan")
    k = (len(xs) - 1) * q
    lo, hi = math.floor(k), math.ceil(k)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def per_robot(swarm, i: int, rounds: int, neighbours: frozenset[int]) -> dict:
    """One robot's rounds from its telemetry (agent.telemetry.read_telemetry via the harness)."""
    tel = swarm.telemetry(i)
    done = [t.round for t in tel]
    over, wait, compute, cpu_rest, cpu_train = [], [], [], [], []
    for prev, t in zip(tel, tel[1:]):
        over.append(t.monotonic - prev.monotonic - t.seconds_compute)
        wait.append(t.seconds_wait)
        compute.append(t.seconds_compute)
        if t.cpu_seconds is not None and t.cpu_seconds_compute is not None:
            cpu_rest.append(t.cpu_seconds - t.cpu_seconds_compute)
            cpu_train.append(t.cpu_seconds_compute)
    short = sum(1 for t in tel if set(t.heard) != set(neighbours))
    return {"robot": i, "degree": len(neighbours), "rounds_ok": done == list(range(1, rounds + 1)),
            "rounds": len(done), "short": short, "overhead_s": over, "wait_s": wait, "compute_s": compute,
            "cpu_outside_compute_s": cpu_rest, "cpu_compute_s": cpu_train,
            "span": [tel[0].monotonic, tel[-1].monotonic] if tel else [0.0, 0.0]}


def run_graph(kind: str, args, out: Path) -> dict:
    """Run one swarm on ``kind`` (ring | rgg) to the end; its per-robot figures and totals."""
    n = args.robots
    info = {"kind": kind}
    if kind == "rgg":
        edges, radius, seed = rgg_edges(n, args.seed)
        topo = TopologyConfig("edges", edges=edges)
        info.update(radius=radius, graph_seed=seed)
    else:
        topo = TopologyConfig("ring")
    shutil.rmtree(out / kind, ignore_errors=True)
    daemon = {"startup_wait_s": 60.0 + 10.0 * n, "round_timeout_s": 120.0, "eval_every": 0, "linger_s": 2.0}
    swarm = make_swarm(out / kind, robots=n, topology=topo, views=4 * n, width=16, seed=args.seed,
                       secure=not args.insecure, training=tiny_training(args.rounds, args.steps), daemon=daemon)
    graph = topo.build(swarm.robots)
    t0 = time.monotonic()
    try:
        swarm.start_all()
        codes, peak, total = wait_robots(swarm.procs, timeout=600 + 30 * n)
    finally:
        swarm.stop()
    info["wall_s"] = time.monotonic() - t0
    bad = [i for i in swarm.robots if codes.get(i) != 0]
    if bad:
        raise SystemExit(f"{kind}: robots {bad} failed (exit {[codes.get(i) for i in bad]}); last log:\n"
                         f"{swarm.log_text(bad[0])}")
    robots = [per_robot(swarm, i, args.rounds, graph.neighbours(i)) for i in swarm.robots]
    for r in robots:
        r["peak_rss_mb"] = peak[r["robot"]] / 1024
    info.update(robots=robots, total_pss_mb=total / 1024, edges=len(graph.edges),
                mean_degree=2 * len(graph.edges) / n, tls=not args.insecure)
    return info


def fmt_robot(r: dict) -> str:
    o, w = r["overhead_s"], r["wait_s"]
    return (f"{r['robot']:>5} {r['degree']:>3} {r['rounds']:>3}{'' if r['rounds_ok'] else '!'} {r['short']:>5} "
            f"{1000 * statistics.median(r['compute_s']):>8.0f} {1000 * statistics.median(o):>8.0f} "
            f"{1000 * pct(o, 0.95):>8.0f} {1000 * statistics.median(w):>8.0f} "
            f"{1000 * statistics.median([a - b for a, b in zip(o, w)]):>8.0f} {r['peak_rss_mb']:>8.0f}")


def report(info: dict, per_robot_rows: bool = True) -> str:
    """The table of one graph: per robot, then over all robots' rounds."""
    rs = info["robots"]
    lines = [f"== {info['kind']}: {len(rs)} robots, {info['edges']} edges, mean degree {info['mean_degree']:.2f}"
             + (f", radius {info['radius']:.3f} (graph seed {info['graph_seed']})" if "radius" in info else "")
             + f", {'mutual TLS' if info['tls'] else 'plain TCP'}, wall {info['wall_s']:.1f} s"]
    head = f"{'robot':>5} {'deg':>3} {'rnd':>3} {'short':>5} {'comp ms':>8} {'ovh med':>8} {'ovh p95':>8} {'wait med':>8} {'rest med':>8} {'RSS MB':>8}"
    if per_robot_rows:
        lines += [head] + [fmt_robot(r) for r in rs]
    over = [x for r in rs for x in r["overhead_s"]]
    wait = [x for r in rs for x in r["wait_s"]]
    comp = [x for r in rs for x in r["compute_s"]]
    rss = [r["peak_rss_mb"] for r in rs]
    cpu = [x for r in rs for x in r.get("cpu_outside_compute_s", [])]
    cpu_train = [x for r in rs for x in r.get("cpu_compute_s", [])]
    cpu_txt = (f"CPU per robot-round: training median {1000 * statistics.median(cpu_train):.1f} ms, "
               f"outside it median {1000 * statistics.median(cpu):.1f} ms, p95 {1000 * pct(cpu, 0.95):.1f} ms; "
               if cpu else "")
    ok = all(r["rounds_ok"] for r in rs)
    # One clock for all (CLOCK_MONOTONIC is the host's): robots computing at once, rounds 2..R.
    busy = sum(comp) / (max(r["span"][1] for r in rs) - min(r["span"][0] for r in rs))
    lines.append(f"all: every robot completed every round: {'yes' if ok else 'NO'}; short rounds "
                 f"{sum(r['short'] for r in rs)}; robots computing at once {busy:.1f} (on {os.cpu_count()} cores); compute median {1000 * statistics.median(comp):.0f} ms; "
                 f"overhead median {1000 * statistics.median(over):.0f} ms, p95 {1000 * pct(over, 0.95):.0f} ms, "
                 f"max {1000 * max(over):.0f} ms; wait median {1000 * statistics.median(wait):.0f} ms, "
                 f"p95 {1000 * pct(wait, 0.95):.0f} ms; {cpu_txt}peak RSS per robot median {statistics.median(rss):.0f} MB, "
                 f"max {max(rss):.0f} MB; all robots together (PSS) {info['total_pss_mb']:.0f} MB")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=32)
    ap.add_argument("--topology", choices=["ring", "rgg", "both"], default="both")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--steps", type=int, default=4, help="training steps per round")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_scale")
    ap.add_argument("--insecure", action="store_true", help="plain TCP instead of mutual TLS")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    if args.robots < 3 or args.rounds < 2 or args.steps < 1:
        sys.exit("need --robots >= 3 (a ring), --rounds >= 2 (the first round is start-up) and --steps >= 1")
    args.out.mkdir(parents=True, exist_ok=True)
    kinds = ["ring", "rgg"] if args.topology == "both" else [args.topology]
    results = []
    for kind in kinds:
        print(f"[bench] {kind}: {args.robots} robots, {args.rounds} rounds x {args.steps} steps", flush=True)
        results.append(run_graph(kind, args, args.out / f"n{args.robots}"))
        print(report(results[-1]), flush=True)
    (args.out / f"scale_n{args.robots}.json").write_text(json.dumps(results, indent=1))
    if len(results) > 1:
        print("\n" + "\n".join(report(r, per_robot_rows=False) for r in results))


if __name__ == "__main__":
    main()
