"""The laggard's choice after a cut heals or a robot was slow: train through the gap or skip it,
to the round a quorum of its neighbours reached, never to one neighbour's claim alone."""

import json

from protocol.evidence import plan_catch_up, quorum_round


def test_in_step_or_one_round_behind_needs_nothing():
    assert plan_catch_up(5, {2: 5, 3: 6, 4: None}, 1.0, 10.0) is None


def test_a_short_gap_is_trained_through_so_no_steps_are_lost():
    # both neighbours at round 8 wait for our round-8 snapshot: 3 rounds of 1 s each, well within 10 s
    assert plan_catch_up(5, {2: 8, 3: 8}, 1.0, 10.0) == ("train", 8)


def test_a_long_gap_is_skipped_or_the_neighbours_would_time_out_round_after_round():
    assert plan_catch_up(5, {2: 8}, 4.0, 10.0) == ("skip", 8)


def test_without_a_measured_round_time_it_skips():
    assert plan_catch_up(0, {2: 3}, None, 10.0) == ("skip", 3)


def test_the_quorum_sets_the_target_never_the_furthest_neighbour():
    assert plan_catch_up(2, {1: 4, 3: 6}, 0.5, 10.0) == ("train", 4)
    assert plan_catch_up(0, {1: 8, 3: 0}, None, 10.0) is None  # one far-future claim among two moves nothing
    assert plan_catch_up(0, {1: 8, 3: None}, None, 10.0) is None  # a neighbour without evidence counts as with us
    assert plan_catch_up(0, {1: 1000, 2: 9, 3: 9}, None, 10.0) == ("skip", 9)


def test_never_past_the_last_round():
    assert plan_catch_up(0, {1: 50, 2: 50}, None, 10.0, last_round=8) == ("skip", 8)


def test_the_quorum_is_a_strict_majority():
    assert quorum_round([]) is None
    assert quorum_round([7]) == 7  # one neighbour: nothing to vote with
    assert quorum_round([3, 9]) == 3
    assert quorum_round([3, 9, 1000]) == 9
    assert quorum_round([3, 5, 9, 1000]) == 5  # three of four are at 5 or later
    assert quorum_round([1, 2, 1000, 1000, 1000]) == 1000


def test_a_claim_counts_only_as_far_as_its_pace_explains():
    from protocol.evidence import ClaimPace

    pace = ClaimPace(burst=2)
    assert not pace.observe(2, 1, now=0.0, own_round=0)  # one past ours: believed as it is
    assert pace.observe(3, 8, now=0.0, own_round=0) and pace.credible(3) == 1  # a first far claim: up to ours + 1
    assert pace.observe(3, 8, now=5.0, own_round=0) and pace.credible(3) == 1  # no round of ours measured: no more
    pace.min_round_s = 1.0
    assert pace.observe(3, 8, now=6.0, own_round=0) and pace.credible(3) == 4  # 2 of burst + 1 s: 3 rounds more
    assert pace.observe(3, 8, now=6.5, own_round=0) and pace.credible(3) == 4
    assert not pace.observe(3, 8, now=12.0, own_round=0) and pace.credible(3) == 8  # a silence earns its rounds
    assert pace.ahead_of_pace() == {}
    assert not pace.observe(3, 2, now=12.5, own_round=0) and pace.credible(3) == 2  # back: a restart
    assert not pace.observe(2, 6, now=13.0, own_round=5)  # it skipped to our round after a freeze: no liar


def test_a_neighbour_whose_snapshots_are_refused_stops_holding_the_barrier():
    from protocol.evidence import RefusalStreaks

    streaks = RefusalStreaks(after=3)
    assert not streaks.not_awaited(3, 1)
    streaks.refused(3, 1)  # its round-1 snapshot held NaN: its answer for round 1, and bad
    assert streaks.not_awaited(3, 1) and not streaks.not_awaited(3, 2)
    reached = [streaks.barrier_ended(1, delivered=[2], awaited=[2, 3])]
    for k in (2, 3):
        streaks.refused(3, k)
        reached.append(streaks.barrier_ended(k, delivered=[2], awaited=[2, 3]))
    assert reached == [[], [], [3]] and streaks.not_awaited(3, 4)  # not waited for before it sends anything
    assert streaks.barrier_ended(4, delivered=[2, 3], awaited=[2]) == [] and not streaks.not_awaited(3, 5)


def test_a_claim_too_far_heard_before_the_join_is_named_when_the_robot_arms(tmp_path):
    """Before the join a neighbour ahead is ahead by right, so its claim is paced but not named;
    at the join it is named at once, whether or not it heartbeats again before its pace explains it."""
    from agent.telemetry import EventLog, Reporter
    from agent.vigilance import Vigilance
    from protocol.evidence import ClaimPace, RefusalStreaks

    lines: list[str] = []
    events = EventLog(tmp_path / "events.jsonl", robot_id=1)
    vigilance = Vigilance(Reporter(1, lines.append, events, round_of=lambda: 0), ClaimPace(), RefusalStreaks(), None)
    vigilance.heard_claim(3, 5, now=0.0, own_round=0)
    vigilance.heard_claim(2, 1, now=0.0, own_round=0)
    assert vigilance.suspects() == {} and not lines
    vigilance.arm()
    events.close()
    assert vigilance.suspects() == {3: "ahead_of_pace"}
    named = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert [(e["event"], e["sender"], e["round"]) for e in named] == [("ahead_of_pace", 3, 0)]
    assert any("robot 3 claims round 5" in line for line in lines)
