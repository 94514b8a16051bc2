"""Key expressions: built in one place, parsed back, foreign keys refused."""

import pytest

from protocol.keys import ForeignKey, Keys, ParsedKey, min_round_of


def test_build_and_parse_round_trip():
    k = Keys("lab-1_A")
    assert k.alive(3) == "dinerf/lab-1_A/alive/3"
    assert k.theta(3, 12, to=5) == "dinerf/lab-1_A/theta/3/12/5"
    assert k.latest(0) == "dinerf/lab-1_A/latest/0"
    assert k.status(7) == "dinerf/lab-1_A/status/7"
    assert k.keyframes(2) == "dinerf/lab-1_A/keyframes/2"
    assert k.alive_all() == "dinerf/lab-1_A/alive/*"
    assert k.theta_of(4) == "dinerf/lab-1_A/theta/4/*/*"
    assert k.theta_for(4, 2) == "dinerf/lab-1_A/theta/4/*/2"
    assert k.status_all() == "dinerf/lab-1_A/status/*"
    assert k.parse(k.theta(3, 12, to=5)) == ParsedKey("theta", 3, 12, 5)
    assert k.parse(k.alive(0)) == ParsedKey("alive", 0, None)
    for build, kind in [(k.latest, "latest"), (k.status, "status"), (k.keyframes, "keyframes")]:
        assert k.parse(build(2**31 - 1)) == ParsedKey(kind, 2**31 - 1, None)


def test_latest_since_carries_a_round_the_server_reads_back():
    k = Keys("s")
    assert k.latest_since(2, 7) == "dinerf/s/latest/2?min_round=7"
    assert k.latest_since(2, 7, held=5) == "dinerf/s/latest/2?min_round=7;held=5"
    assert min_round_of("7") == 7 and min_round_of(None) is None
    for bad in ["", "-1", "07", "x", "1e3", str(2**31)]:  # malformed: treated as absent
        assert min_round_of(bad) is None
    with pytest.raises(ValueError):
        k.latest_since(2, -1)


@pytest.mark.parametrize("swarm", ["", "a/b", "a*", "$x", "a?b", "a#", "with space", "x" * 65, None, 3])
def test_invalid_swarm_names_are_refused(swarm):
    with pytest.raises(ValueError, match="swarm"):
        Keys(swarm)


@pytest.mark.parametrize("robot_id", [-1, 1.0, True, "3", 2**31])
def test_invalid_ids_are_refused_when_building(robot_id):
    with pytest.raises(ValueError):
        Keys("s").alive(robot_id)
    with pytest.raises(ValueError):
        Keys("s").theta(0, robot_id, to=1)


@pytest.mark.parametrize("key", [
    "dinerf/other/theta/1/2/3",    # other swarm
    "robots/s/theta/1/2/3",        # other root
    "dinerf/s/weights/1",          # unknown kind
    "dinerf/s/theta/1",            # round missing
    "dinerf/s/theta/1/2",          # receiver missing
    "dinerf/s/theta/1/2/x",        # bad receiver
    "dinerf/s/alive/1/2",          # extra segment
    "dinerf/s/theta/01/2/3",       # non-canonical id
    "dinerf/s/theta/-1/2/3",
    "dinerf/s/theta/1/x/3",
    "dinerf/s/theta/*/2/3",        # wildcard is not a concrete key
    "dinerf/s/alive/99999999999",  # out of range
    "dinerf/s",
    "",
])
def test_foreign_keys_are_refused(key):
    with pytest.raises(ForeignKey):
        Keys("s").parse(key)


def test_parse_refuses_non_strings():
    with pytest.raises(ForeignKey):
        Keys("s").parse(None)
