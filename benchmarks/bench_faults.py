"""The fault scenarios against the fault-free run: the issue's target is that every fault scenario
completes, loses no checkpoint, and leaves the survivors within 0.5 dB of the fault-free run.

    sudo .venv/bin/python benchmarks/bench_faults.py [--out /tmp/faults] [--mode netns] \\
        [--scenarios fault-kill-restart,fault-freeze,fault-link-cut,fault-lossy-link] [--repeat-free 1]

Runs ``fault-free`` (``--repeat-free`` times: a check that it is deterministic; two runs gave the
same PSNR to the last digit, yet any perturbation, even a different float summation order,
moves robots by ~0.2 dB, so read differences of that size as noise) and each fault scenario,
all in the same mode (``netns`` needs root; link faults need it), then prints
``dinerf-agent scenario compare`` for each against the first fault-free run. About 3.5 minutes per
scenario on 2 cores. A run folder that already holds a report is reused (delete it to re-run).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cli.scenario.compare import compare_runs, format_comparison  # noqa: E402

FAULTS = ["fault-kill-restart", "fault-freeze", "fault-link-cut", "fault-lossy-link"]


def run(name: str, out: Path, mode: str) -> float:
    """Run one scenario into ``out`` (skipped if a report is already there); its wall time in s."""
    if (out / "report.json").is_file():
        print(f"[bench] {name}: reusing {out}", flush=True)
        return float("nan")
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "cli", "scenario", "run", name, "--out", str(out), "--mode", mode, "--force"]
    print(f"[bench] {' '.join(cmd)}", flush=True)
    subprocess.run(cmd, cwd=ROOT, check=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return time.monotonic() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_faults")
    ap.add_argument("--mode", default="netns" if os.geteuid() == 0 else "local")
    ap.add_argument("--scenarios", default=",".join(FAULTS))
    ap.add_argument("--repeat-free", type=int, default=1)
    ap.add_argument("--tolerance-db", type=float, default=0.5)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    names = [n for n in args.scenarios.split(",") if n]
    if args.mode != "netns" and any(n in ("fault-link-cut", "fault-lossy-link") for n in names):
        sys.exit("link faults need --mode netns (root)")

    seconds: dict[str, float] = {}
    free_dirs = [args.out / ("fault-free" if k == 0 else f"fault-free-{k + 1}") for k in range(args.repeat_free)]
    seconds[free_dirs[0].name] = run("fault-free", free_dirs[0], args.mode)
    for name in names:
        seconds[name] = run(name, args.out / name, args.mode)
    for d in free_dirs[1:]:  # last: the fault runs matter more if time runs short
        seconds[d.name] = run("fault-free", d, args.mode)

    results = []
    print()
    for d in free_dirs[1:]:  # the noise floor: a fault-free run against the first one
        c = compare_runs(d, free_dirs[0], args.tolerance_db)
        print(format_comparison(c) + "\n")
        results.append(c.to_json())
    for name in names:
        c = compare_runs(args.out / name, free_dirs[0], args.tolerance_db)
        print(format_comparison(c) + f"\nwall time: {seconds[name]:.0f} s\n")
        results.append(c.to_json())
    if args.json:
        args.json.write_text(json.dumps({"seconds": seconds, "comparisons": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
