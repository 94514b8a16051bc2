"""The laggard's choice after a cut heals or a robot was slow: train through the gap or skip it."""

from protocol.exchange import plan_catch_up


def test_in_step_or_one_round_behind_needs_nothing():
    assert plan_catch_up(5, {2: 5, 3: 6, 4: None}, 1.0, 10.0) is None


def test_a_short_gap_is_trained_through_so_no_steps_are_lost():
    # neighbour at round 8 waits for our round-8 snapshot: 3 rounds of 1 s each, well within 10 s
    assert plan_catch_up(5, {2: 8, 3: 6}, 1.0, 10.0) == ("train", 8)


def test_a_long_gap_is_skipped_or_the_neighbour_would_time_out_round_after_round():
    assert plan_catch_up(5, {2: 8}, 4.0, 10.0) == ("skip", 8)


def test_without_a_measured_round_time_it_skips():
    assert plan_catch_up(0, {2: 3}, None, 10.0) == ("skip", 3)


def test_the_furthest_neighbour_sets_the_target():
    assert plan_catch_up(2, {1: 4, 3: 6}, 0.5, 10.0) == ("train", 6)
