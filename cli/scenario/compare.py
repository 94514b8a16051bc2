"""A fault scenario against its fault-free twin: did the survivors lose quality, did anyone lose rounds?

Reads two finished run folders (``report.json`` written by :func:`cli.scenario.report.build_report`,
and each robot's ``events.jsonl`` / ``telemetry.jsonl``) and says, per robot:

- its final PSNR on the whole scene and on the views only the others saw, beside the fault-free
  run's, and whether it stays within ``tolerance_db`` (the issue's target: 0.5 dB);
- whether it finished every round (its last round's checkpoint was written);
- for each restart, how many completed rounds its checkpoint lost (a SIGKILL may cost the round
  in progress only, never a completed one).

A run whose robots hear the same neighbours every round repeats itself exactly (two fault-free
runs: the same PSNR to the last digit), but any perturbation, even a float summation order,
moved robots by ~0.2 dB (measured): read differences of that size as noise.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from agent.checkpoint import RunFolder
from agent.files import read_json
from agent.telemetry import read_events, read_telemetry
from cli.scenario.report import load_run_spec


class CompareError(ValueError):
    """A folder that is not a finished, reported scenario run."""


@dataclass
class RobotVerdict:
    robot: int
    psnr: float | None
    psnr_fault_free: float | None
    psnr_others_only: float | None
    psnr_others_only_fault_free: float | None
    final_round: int | None
    rounds: int
    starts: int | None
    #: completed rounds a restart did not find in the checkpoint, one entry per restart
    rounds_lost_per_restart: list[int] = field(default_factory=list)

    @property
    def delta_db(self) -> float | None:
        if self.psnr is None or self.psnr_fault_free is None:
            return None
        return self.psnr - self.psnr_fault_free

    @property
    def finished(self) -> bool:
        return self.final_round == self.rounds

    def within(self, tolerance_db: float) -> bool:
        return self.delta_db is not None and self.delta_db >= -tolerance_db


@dataclass
class Comparison:
    scenario: str
    fault_free: str
    faults: list[dict[str, Any]]
    robots: list[RobotVerdict]
    tolerance_db: float

    @property
    def ok(self) -> bool:
        return all(r.finished and r.within(self.tolerance_db) and not any(r.rounds_lost_per_restart)
                   for r in self.robots)

    def to_json(self) -> dict[str, Any]:
        return {"scenario": self.scenario, "fault_free": self.fault_free, "faults": self.faults,
                "tolerance_db": self.tolerance_db, "ok": self.ok,
                "robots": [{**asdict(r), "delta_db": r.delta_db, "finished": r.finished} for r in self.robots]}


def _report(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / "report.json"
    if not path.is_file():
        raise CompareError(f"{run_dir}: no report.json (run `dinerf-agent scenario report {run_dir}` first)")
    return read_json(path, CompareError)


def rounds_lost_per_restart(robot_dir: Path) -> list[int]:
    """For each resume of this robot: its last completed round before the restart minus the
    round its checkpoint gave back (0 = nothing lost)."""
    folder = RunFolder(robot_dir, create=False)
    telemetry = sorted(read_telemetry(folder.telemetry), key=lambda r: r.time)
    lost = []
    for ev in read_events(folder.events):
        if ev.get("event") != "resumed":
            continue
        before = [r.round for r in telemetry if r.time < ev.get("time", 0.0)]
        lost.append(max(0, max(before, default=0) - int(ev.get("from_round", 0))))
    return lost


def compare_runs(run_dir: Path, fault_free_dir: Path, tolerance_db: float = 0.5) -> Comparison:
    run, base = _report(run_dir), _report(fault_free_dir)
    rounds = load_run_spec(Path(run_dir)).training.rounds
    verdicts = []
    for rid, doc in sorted(run["robots"].items(), key=lambda kv: int(kv[0])):
        final = doc.get("final") or {}
        base_final = (base["robots"].get(rid) or {}).get("final") or {}
        verdicts.append(RobotVerdict(
            robot=int(rid), psnr=final.get("psnr"), psnr_fault_free=base_final.get("psnr"),
            psnr_others_only=final.get("psnr_others_only"),
            psnr_others_only_fault_free=base_final.get("psnr_others_only"),
            final_round=doc.get("final_round"), rounds=rounds, starts=doc.get("starts"),
            rounds_lost_per_restart=rounds_lost_per_restart(Path(run_dir) / "robots" / rid)))
    faults = [{k: v for k, v in f.items() if k != "event"} for f in run.get("faults", [])]
    return Comparison(f"{run.get('scenario')} ({run_dir})", f"{base.get('scenario')} ({fault_free_dir})",
                      faults, verdicts, tolerance_db)


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def format_comparison(c: Comparison) -> str:
    """A markdown table, one row per robot, and a verdict line."""
    lines = [f"{c.scenario} against {c.fault_free} (tolerance {c.tolerance_db} dB); faults: "
             + (", ".join(json.dumps(f, sort_keys=True) for f in c.faults) or "none"),
             "",
             "| robot | PSNR | fault-free | delta | others-only | fault-free | rounds | starts | rounds lost at restart |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in c.robots:
        lines.append(f"| {r.robot} | {_f(r.psnr)} | {_f(r.psnr_fault_free)} | {_f(r.delta_db, '+.2f')} | "
                     f"{_f(r.psnr_others_only)} | {_f(r.psnr_others_only_fault_free)} | "
                     f"{r.final_round}/{r.rounds} | {r.starts} | "
                     f"{', '.join(map(str, r.rounds_lost_per_restart)) or '-'} |")
    lines.append("")
    lines.append(f"verdict: {'met' if c.ok else 'NOT met'} (target: every robot finishes, loses no completed "
                 f"round, and stays within {c.tolerance_db} dB of the fault-free run)")
    return "\n".join(lines)
