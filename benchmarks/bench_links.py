"""Wall time of a swarm on capped links: the 5-robot lego ring, float32 uncapped against compressed
snapshots on 20 and 5 Mbit/s links, in one invocation on the same data and rounds.

    sudo .venv/bin/python benchmarks/bench_links.py [--out runs/bench_links] [--rounds 10] \\
        [--runs none@0,delta+uniform@20,delta+uniform@5]

Each run is ``lego-5-ring`` in netns mode (root: the caps are `tc`, or the link emulator where
the kernel lacks sch_netem) with
``RUN = compression@rate_mbit`` (rate 0: uncapped), ``--rounds`` rounds and no baselines.
Prints, per run: seconds per round (from the first robot's first round to the last robot's last
round, so start-up is left out) and its ratio to the first run, bytes per link per round, the
share of (robot, round) pairs that heard both neighbours, and the mean final PSNR. A run folder
that already holds a report is reused (delete it to re-run). About 4 minutes per run on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.telemetry import RoundRecord, read_telemetry  # noqa: E402

RING = [(1, 2), (2, 3), (3, 4), (4, 5), (1, 5)]


def run_one(compression: str, rate_mbit: float, rounds: int, out: Path) -> None:
    """``lego-5-ring`` with this compression, every link capped at ``rate_mbit`` (0: uncapped)."""
    if (out / "report.json").is_file():
        print(f"[bench] reusing {out}", flush=True)
        return
    sets = [f"training.rounds={rounds}", "baseline.enabled=false", "report.eval_every=1000",
            f'daemon.exchange.compression="{compression}"']
    if rate_mbit > 0:
        caps = ", ".join(f"{{ link = [{a}, {b}], from_round = 0, rate_mbit = {rate_mbit:g} }}" for a, b in RING)
        sets.append(f"faults.netem=[{caps}]")
    cmd = [sys.executable, "-m", "cli", "scenario", "run", "lego-5-ring", "--out", str(out), "--mode", "netns",
           "--force"] + [a for s in sets for a in ("--set", s)]
    print(f"[bench] {' '.join(cmd)}", flush=True)
    subprocess.run(cmd, cwd=ROOT, check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})


def summarise(out: Path) -> dict:
    """Seconds per round, bytes per link per round, the share of rounds with both neighbours heard, PSNR."""
    report = json.loads((out / "report.json").read_text())
    recs: dict[int, list[RoundRecord]] = {
        int(i): read_telemetry(out / "robots" / i / "telemetry.jsonl") for i in report["robots"]}
    first = min(r[0].time for r in recs.values() if r)
    last = max(r[-1].time for r in recs.values() if r)
    rounds = max(len(r) for r in recs.values())
    link_bytes = [b for r in recs.values() for rec in r for b in rec.bytes_out_links.values()]
    both = [len(rec.heard) == 2 for r in recs.values() for rec in r[1:]]
    psnrs = [d["final"].get("psnr") for d in report["robots"].values() if d.get("final")]
    return {
        "seconds_per_round": (last - first) / max(rounds - 1, 1),
        "bytes_per_link_round": statistics.mean(link_bytes) if link_bytes else 0.0,
        "heard_both": sum(both) / max(len(both), 1),
        "psnr": statistics.mean(p for p in psnrs if p is not None) if psnrs else float("nan"),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_links")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--runs", default="none@0,delta+uniform@20,delta+uniform@5",
                    help="comma-separated COMPRESSION@RATE_MBIT (0: uncapped); the first is the baseline")
    args = ap.parse_args()
    if os.geteuid() != 0:
        sys.exit("bench_links needs root: the links are capped with tc in network namespaces")
    runs = []
    for item in args.runs.split(","):
        compression, _, rate = item.partition("@")
        runs.append((compression, float(rate or 0)))
    rows = []
    for compression, rate in runs:
        out = args.out / f"{compression.replace('+', '_')}_{rate:g}mbit"
        run_one(compression, rate, args.rounds, out)
        rows.append((compression, rate, summarise(out)))
    base = rows[0][2]["seconds_per_round"]
    print(f"\nlego-5-ring, {args.rounds} rounds, netns; seconds per round from the first round's end to the last's")
    print(f"{'compression':<16}{'link':>10}{'s/round':>9}{'x base':>8}{'MB/link/round':>15}{'heard both':>12}{'PSNR':>8}")
    for compression, rate, s in rows:
        link = f"{rate:g} Mbit" if rate > 0 else "uncapped"
        print(f"{compression:<16}{link:>10}{s['seconds_per_round']:>9.2f}{s['seconds_per_round'] / base:>8.2f}"
              f"{s['bytes_per_link_round'] / 1e6:>15.3f}{s['heard_both']:>12.0%}{s['psnr']:>8.2f}")


if __name__ == "__main__":
    main()
