"""Splits of real trajectories: sectors over the arc the cameras cover, segments of the capture order."""

from __future__ import annotations

import pytest

from agent.data.procedural import ProceduralConfig, procedural_views
from agent.data.split import SplitConfig, split_views
from agent.data.views import DataError


@pytest.fixture(scope="module")
def arc():
    """A handheld-like capture: 60 views on a 90 deg arc that crosses azimuth 0, in capture order."""
    return procedural_views(ProceduralConfig(num_views=60, width=8, height=8, supersample=1, arc_deg=90.0,
                                             arc_start_deg=315.0, seed=4))


def _in(az: float, sector: tuple[float, float]) -> bool:
    a, b = sector
    return ((az - a) % 360) < (b - a)


def test_sectors_over_an_arc_give_each_robot_its_share(arc):
    r = split_views(arc, SplitConfig(robots=2, test_every=8))
    assert r.layout == "arc"
    counts = [len(rob.indices) for rob in r.robots.values()]
    assert sorted(counts) == [26, 26] and sum(counts) == 52, "the 52 training views halved"
    for rid, rob in r.robots.items():
        assert all(_in(float(r.azimuth_deg[i]), rob.sector_deg) for i in rob.indices)
    for idx, seen in zip(r.eval_indices, r.seen_by):  # seen_by: the sector the test view lies in
        assert seen == [rid for rid, rob in r.robots.items() if _in(float(r.azimuth_deg[idx]), rob.sector_deg)]
        assert len(seen) == 1
    assert any("arc of" in n for n in r.notes)
    three = split_views(arc, SplitConfig(robots=3, test_every=8, sector_start_deg=20.0))
    assert any("sector_start_deg (20.0) ignored" in n for n in three.notes)
    assert sorted(len(rob.indices) for rob in three.robots.values()) in ([17, 17, 18], [17, 18, 17])


@pytest.mark.parametrize("overlap", [0.1, 0.3])
def test_overlap_on_an_arc_is_achieved_and_meant_as_before(arc, overlap):
    r = split_views(arc, SplitConfig(robots=3, overlap=overlap))
    assert abs(r.mean_overlap - overlap) < 0.05 and r.margin_deg > 0
    for rid, rob in r.robots.items():
        others = {i for j, o in r.robots.items() if j != rid for i in o.indices}
        assert rob.overlap == pytest.approx(sum(i in others for i in rob.indices) / len(rob.indices))


def test_a_full_circle_keeps_equal_sectors_from_sector_start():
    v = procedural_views(ProceduralConfig(num_views=60, width=8, height=8, supersample=1, seed=0))
    r = split_views(v, SplitConfig(robots=3, sector_start_deg=30.0))
    assert r.layout == "circle"
    assert [rob.sector_deg for rob in r.robots.values()] == [(30.0, 150.0), (150.0, 270.0), (270.0, 390.0)]


def test_trajectory_segments_are_contiguous_in_capture_order(arc):
    r = split_views(arc, SplitConfig(robots=3, by="trajectory", test_every=8))
    assert r.layout == "trajectory" and r.margin_views == 0 and r.mean_overlap == 0.0
    train = [i for i in range(60) if i % 8]
    got = [rob.indices for rob in r.robots.values()]
    assert [i for seg in got for i in seg] == train, "segments follow one another in capture order"
    assert [len(seg) for seg in got] == [17, 18, 17]
    for rid, rob in r.robots.items():  # the reported azimuth span holds the robot's views
        a, b = rob.sector_deg
        assert all(((float(r.azimuth_deg[i]) - a) % 360) <= b - a + 1e-9 for i in rob.indices)
    assert all(len(s) == 1 for s in r.seen_by)


def test_trajectory_test_views_are_seen_by_the_robot_that_walked_past():
    """At a steady elevation the nearest view in pose is a neighbour in capture order."""
    walk = procedural_views(ProceduralConfig(num_views=60, width=8, height=8, supersample=1, arc_deg=120.0,
                                             elevation_deg=(30.0, 30.0), seed=1))
    r = split_views(walk, SplitConfig(robots=3, by="trajectory", test_every=8))
    for idx, seen in zip(r.eval_indices, r.seen_by):
        holders = {rid for rid, rob in r.robots.items() if idx - 1 in rob.indices or idx + 1 in rob.indices}
        assert len(seen) == 1 and seen[0] in holders
    assert r.seen_by[0] == [1] and r.seen_by[-1] == [3]


def test_trajectory_overlap_is_shared_views_at_the_borders(arc):
    r = split_views(arc, SplitConfig(robots=3, by="trajectory", overlap=0.2, test_every=8))
    assert abs(r.mean_overlap - 0.2) < 0.05 and r.margin_views > 0
    one, two, three = (r.robots[k].indices for k in (1, 2, 3))
    s, train = r.margin_views, [i for i in range(60) if i % 8]
    cut = 17  # of the 52 training views, robot 1's core segment is the first 17
    assert set(one) & set(two) == set(train[cut - s // 2:cut + (s + 1) // 2]), "the s views round the cut"
    assert not set(one) & set(three)
    for seg in (one, two, three):
        assert seg == train[train.index(seg[0]):train.index(seg[-1]) + 1], "still contiguous"
    border = [s for s in r.seen_by if len(s) > 1]
    assert all(s in ([1, 2], [2, 3]) for s in border)


def test_trajectory_errors():
    with pytest.raises(DataError, match="by must be one of"):
        SplitConfig(by="spiral")  # type: ignore[arg-type]
    v = procedural_views(ProceduralConfig(num_views=4, width=8, height=8, supersample=1, arc_deg=30.0))
    with pytest.raises(DataError, match="gets no views"):
        split_views(v, SplitConfig(robots=5, by="trajectory", test_every=0))
