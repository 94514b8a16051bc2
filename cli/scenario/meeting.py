"""When robots that train while they explore first share a place, and how soon they were aligned.

A scenario whose robots replay their bags (``record.replay``) knows, from its recordings, which
view each robot recorded at which stamp, and from the split which views two robots both hold.
Each robot's keyframe cache says when each of its keyframes was admitted. Two neighbours *meet*
when both have admitted a keyframe of a view they share (the split's overlap: at first these may
be the overlap's two ends, tens of degrees apart), and *stand at the same place* when both have
admitted the same view. A robot not placed by then should be aligned within a few rounds of it
(issue 44); one aligned before any such keyframe was placed from something else than overlap.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from agent.checkpoint import RunFolder
from agent.telemetry import RoundRecord, read_events

__all__ = ["meetings", "markdown"]


def _admitted(run_dir: Path, stamps_s: list[float], views: list[str]) -> list[tuple[float, str]]:
    """(admitted wall time s, view name) of each keyframe a robot took, in admission order."""
    path = RunFolder(run_dir, create=False).keyframe_cache / "transforms.json"
    if not path.is_file():
        return []
    frames = json.loads(path.read_text()).get("frames", [])
    stamps = np.asarray(stamps_s)
    out = []
    for f in frames:
        if "stamp_ns" not in f or "admitted_ns" not in f or not len(stamps):
            continue  # a cache of before admission times were kept
        k = int(np.abs(stamps - f["stamp_ns"] * 1e-9).argmin())  # the recorded image it came from
        out.append((f["admitted_ns"] * 1e-9, views[k]))
    return out


def _round_at(recs: list[RoundRecord], t: float) -> int | None:
    """The round a robot was in at wall time ``t`` (the first that ended after it)."""
    return next((r.round for r in recs if r.time >= t), None)


def meetings(out: Path, ids: list[int], links: list[tuple[int, int]], recordings: dict,
             telemetry: dict[int, list[RoundRecord]], reference: int) -> dict:
    """Per robot: when it first met a neighbour, when it was aligned, and the rounds between."""
    admitted = {i: _admitted(out / "robots" / str(i), recordings[str(i)]["stamps_s"], recordings[str(i)]["views"])
                for i in ids if str(i) in recordings}
    result = {}
    for i in ids:
        met: list[tuple[float, int]] = []
        same: list[float] = []
        for a, b in links:
            if i not in (a, b) or a not in admitted or b not in admitted:
                continue
            j = b if i == a else a
            shared = set(recordings[str(i)]["views"]) & set(recordings[str(j)]["views"])
            first = [min((t for t, v in admitted[k] if v in shared), default=None) for k in (i, j)]
            if None not in first:
                met.append((max(first), j))
            when = [{v: t for t, v in admitted[k]} for k in (i, j)]
            same += [max(when[0][v], when[1][v]) for v in when[0].keys() & when[1].keys()]
        events = read_events(RunFolder(out / "robots" / str(i), create=False).events)
        aligned = [e for e in events if e.get("event") == "aligned"]
        joined = [e for e in events if e.get("event") == "entered_consensus"]
        t_met, via = min(met) if met else (None, None)
        met_round = _round_at(telemetry.get(i, []), t_met) if t_met is not None else None
        same_round = _round_at(telemetry.get(i, []), min(same)) if same else None
        aligned_round = aligned[-1].get("round") if aligned else None

        def after(r: int | None) -> int | None:
            return aligned_round - r if aligned_round is not None and r is not None else None

        result[str(i)] = {
            "reference": i == reference,
            "met": via, "met_round": met_round, "same_view_round": same_round,
            "aligned_round": aligned_round, "entered_consensus_round": joined[-1].get("round") if joined else None,
            "rounds_to_align": after(met_round), "rounds_to_align_same_view": after(same_round),
            "keyframes": len(admitted.get(i, [])),
        }
    return result


def markdown(meet: dict, pose_errors: dict[str, tuple[float, float]]) -> list[str]:
    """The report's section: one row per robot."""
    lines = ["## Exploring: when robots met and were aligned", "",
             "Robots trained while their bags played. *Met*: the round in which the robot and a neighbour had "
             "both admitted a keyframe of a view they share (the split's overlap, whose two ends may be tens of "
             "degrees apart); *same view*: the round in which both had admitted one same view; *aligned*: the "
             "round of its (last) coarse alignment.", "",
             "| robot | keyframes | met (neighbour, round) | same view (round) | aligned at round | "
             "rounds after meeting / same view | final rot err (deg) | final trans err |",
             "|---|---|---|---|---|---|---|---|"]
    for i, m in sorted(meet.items(), key=lambda kv: int(kv[0])):
        rot, trans = pose_errors.get(i, (None, None))
        met = f"robot {m['met']}, round {m['met_round']}" if m["met"] is not None else "never"
        aligned = "reference" if m["reference"] else m["aligned_round"] if m["aligned_round"] is not None else "never"
        after = "" if m["reference"] else " / ".join("-" if m[k] is None else str(m[k])
                                                      for k in ("rounds_to_align", "rounds_to_align_same_view"))
        same = "never" if m["same_view_round"] is None else m["same_view_round"]
        lines.append(f"| {i} | {m['keyframes']} | {met} | {same} | {aligned} | {after} | "
                     f"{'-' if rot is None else f'{rot:.2f}'} | {'-' if trans is None else f'{trans:.3f}'} |")
    return lines + [""]
