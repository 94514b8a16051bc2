"""cli.scenario.meeting: when two exploring robots first share a place, and the rounds to alignment."""

from __future__ import annotations

import json

from agent.telemetry import RoundRecord
from cli.scenario.meeting import markdown, meetings


def _robot(out, i: int, admitted: list[tuple[float, float]], events: list[dict]) -> None:
    """admitted: (stamp s, admitted wall time s) of each keyframe."""
    cache = out / "robots" / str(i) / "keyframes"
    cache.mkdir(parents=True)
    frames = [{"stamp_ns": int(s * 1e9), "admitted_ns": int(t * 1e9)} for s, t in admitted]
    (cache / "transforms.json").write_text(json.dumps({"frames": frames}))
    (out / "robots" / str(i) / "events.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))


def test_robots_meet_when_both_have_admitted_a_shared_view_and_the_rounds_to_alignment_follow(tmp_path):
    # robot 1 walks a -> d, robot 2 walks f -> c: they share c and d. Both hold a shared view at t=107
    # (robot 1 c at 103, robot 2 d at 107); both hold the same one, d, only at t=110
    recordings = {"1": {"views": ["a", "b", "c", "d"], "stamps_s": [0.0, 1.0, 2.0, 3.0]},
                  "2": {"views": ["f", "e", "d", "c"], "stamps_s": [50.0, 51.0, 52.0, 53.0]}}
    _robot(tmp_path, 1, [(0.0, 100.0), (1.0, 101.0), (2.0, 103.0), (3.0, 110.0)], [])
    _robot(tmp_path, 2, [(50.0, 100.0), (51.0, 102.0), (52.001, 107.0)],  # a stamp is matched to the nearest image
           [{"event": "aligned", "round": 0, "how": "start"}, {"event": "aligned", "round": 6},
            {"event": "entered_consensus", "round": 6}])
    telemetry = {i: [RoundRecord(robot=i, round=r, time=100.0 + 2 * r) for r in range(1, 11)] for i in (1, 2)}
    got = meetings(tmp_path, [1, 2], [(1, 2)], recordings, telemetry, reference=1)
    assert got["2"]["met"] == 1 and got["2"]["met_round"] == 4  # t=107: in round 4 (ends at 108)
    assert got["2"]["aligned_round"] == 6 and got["2"]["rounds_to_align"] == 2  # the last alignment counts
    assert got["2"]["same_view_round"] == 5 and got["2"]["rounds_to_align_same_view"] == 1  # t=110: round 5
    assert got["1"]["reference"] and got["1"]["met_round"] == 4 and got["2"]["keyframes"] == 3
    table = "\n".join(markdown(got, {"2": (0.5, 0.01)}))
    assert "| 2 | 3 | robot 1, round 4 | 5 | 6 | 2 / 1 | 0.50 | 0.010 |" in table and "| 1 | 4 |" in table


def test_robots_that_never_share_a_place_never_meet(tmp_path):
    recordings = {"1": {"views": ["a"], "stamps_s": [0.0]}, "2": {"views": ["b"], "stamps_s": [0.0]}}
    _robot(tmp_path, 1, [(0.0, 100.0)], [])
    _robot(tmp_path, 2, [(0.0, 100.0)], [])
    got = meetings(tmp_path, [1, 2], [(1, 2)], recordings, {}, reference=1)
    assert got["2"]["met"] is None and got["2"]["rounds_to_align"] is None
    assert "never" in "\n".join(markdown(got, {}))
