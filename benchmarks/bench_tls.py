"""Mutual TLS + access control against plain TCP: the same real swarm (`dinerf-agent up` robots on
loopback, tests/system/harness.py), run alternately insecure and secure, in one benchmark run.

    nice .venv/bin/python benchmarks/bench_tls.py [--robots 3] [--rounds 8] [--repeats 2] [--log2-hashmap 14]

Per mode, over every robot's rounds after the first (the first includes start-up): the round
time (between consecutive telemetry lines), the time waiting at the barrier, the duration of the
snapshot puts, and the snapshot bytes received per link per round. Runs alternate (tcp, tls,
tcp, tls ...) so that a change of machine load hits both modes alike.
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

from tests.system.harness import make_swarm  # noqa: E402


def run_once(tmp: Path, secure: bool, robots: int, rounds: int, log2_hashmap: int) -> dict[str, list[float]]:
    training = {"rounds": rounds, "train": {"field": {"grid": {"log2_hashmap_size": log2_hashmap}}}}
    swarm = make_swarm(tmp, robots=robots, topology="full", training=training, secure=secure)
    t0 = time.monotonic()
    try:
        swarm.start_all()
        swarm.wait_all(timeout=600)
    finally:
        swarm.stop()
    wall = time.monotonic() - t0
    out: dict[str, list[float]] = {"round_s": [], "wait_s": [], "put_s": [], "bytes_per_link": [], "wall_s": [wall]}
    for i in swarm.robots:
        tel = swarm.telemetry(i)
        assert [t.round for t in tel] == list(range(1, rounds + 1)), f"robot {i} did not train every round"
        for prev, t in zip(tel, tel[1:]):
            out["round_s"].append(t.monotonic - prev.monotonic)
            out["wait_s"].append(t.seconds_wait)
            out["put_s"].extend(t.seconds_last_put.values())
            out["bytes_per_link"].extend(float(b) for b in t.bytes_in.values())
        if secure:
            assert "secure: mutual TLS" in swarm.log_text(i)
        else:
            assert "INSECURE" in swarm.log_text(i)
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--log2-hashmap", type=int, default=14, help="hash table size of the model (bytes per snapshot)")
    args = p.parse_args()
    figures: dict[str, dict[str, list[float]]] = {"tcp": {}, "tls": {}}
    with tempfile.TemporaryDirectory() as d:
        for r in range(args.repeats):
            for mode in ("tcp", "tls"):
                got = run_once(Path(d) / f"{mode}{r}", mode == "tls", args.robots, args.rounds, args.log2_hashmap)
                for k, v in got.items():
                    figures[mode].setdefault(k, []).extend(v)
                print(f"run {r + 1}/{args.repeats} {mode}: wall {got['wall_s'][0]:.1f} s, median round "
                      f"{statistics.median(got['round_s']):.3f} s", flush=True)
    print(f"\n{args.robots} robots, full topology, {args.rounds} rounds x {args.repeats} runs per mode, "
          f"log2 hash table {args.log2_hashmap}")
    print(f"{'':6} {'round s (median)':>17} {'round s (mean)':>15} {'wait s':>8} {'put ms':>8} {'KB/link/round':>14}")
    for mode, f in figures.items():
        print(f"{mode:6} {statistics.median(f['round_s']):17.3f} {statistics.fmean(f['round_s']):15.3f} "
              f"{statistics.median(f['wait_s']):8.3f} {1000 * statistics.median(f['put_s']):8.2f} "
              f"{statistics.median(f['bytes_per_link']) / 1e3:14.1f}")
    tcp, tls = (statistics.median(figures[m]["round_s"]) for m in ("tcp", "tls"))
    print(f"TLS round time / TCP round time: {tls / tcp:.3f} (median)")


if __name__ == "__main__":
    main()
