"""The laggard's choice after a cut heals or a robot was slow: train through the gap or skip it,
to the round a quorum of its neighbours reached, never to one neighbour's claim alone."""

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
