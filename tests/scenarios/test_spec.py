"""scenario.toml validation: every mistake is a one-line error that names the key or the fault."""

from __future__ import annotations

from pathlib import Path

import pytest

from cli.config import ConfigError
from cli.scenario.spec import find_scenario, list_scenarios, load_scenario, resolve_dataset

BASE = """
[scenario]
name = "t"
dataset = "procedural:views=30,width=32"
robots = 3
[topology]
kind = "line"
[training]
rounds = 5
steps_per_round = 4
"""


def write(tmp_path: Path, extra: str = "", base: str = BASE) -> Path:
    p = tmp_path / "scenario.toml"
    p.write_text(base + extra)
    return p


def error(tmp_path: Path, extra: str = "", base: str = BASE) -> str:
    with pytest.raises(ConfigError) as e:
        load_scenario(write(tmp_path, extra, base))
    msg = str(e.value)
    assert "\n" not in msg.strip(), msg
    return msg


def test_valid_scenario_is_typed(tmp_path):
    s = load_scenario(write(tmp_path, """
[training.train.field.grid]
log2_hashmap_size = 12
[faults]
kill = [{ robot = 3, round = 1 }]
restart = [{ robot = 3, round = 3 }]
cut = [{ link = [2, 1], from_round = 1, to_round = 3 }]
netem = [{ link = [2, 3], from_round = 0, delay_ms = 100, loss = 0.1 }]
"""))
    assert s.ids == [1, 2, 3] and s.links == [(1, 2), (2, 3)] and s.rounds == 5
    assert s.training.train.field.grid.log2_hashmap_size == 12
    assert s.faults.kill[0].robot == 3 and s.faults.netem[0].loss == 0.1
    assert s.faults.needs_netns
    s.check_mode("netns")
    with pytest.raises(ConfigError, match="need --mode netns"):
        s.check_mode("local")


@pytest.mark.parametrize(
    "extra, needle",
    [
        ("[split]\noverlapp = 0.1\n", "overlapp"),
        ("[training.train]\nray_per_step = 10\n", "ray_per_step"),
        ("[network]\nlease = 10\n", "lease"),
        ("[network]\nlisten = ['tcp/1.2.3.4:1']\n", "network.listen"),
        ("[split]\nframe = 'sideways'\n", "frame"),
        ("[split]\noverlap = 0.9\n", "overlap"),
        ("[faults]\nkill = [{ robot = 7, round = 1 }]\n", "robot 7"),
        ("[faults]\nkill = [{ robot = 2, round = 9 }]\n", "round 9"),
        ("[faults]\nrestart = [{ robot = 2, round = 2 }]\n", "alternate"),
        ("[faults]\nkill = [{ robot = 2, round = 1 }, { robot = 2, round = 3 }]\n", "alternate"),
        ("[faults]\ncut = [{ link = [1, 3], from_round = 1 }]\n", "not in the line topology"),
        ("[faults]\ncut = [{ link = [1, 2], from_round = 3, to_round = 2 }]\n", "to_round"),
        ("[faults]\ncut = [{ link = [1, 2], from_round = 1 }, { link = [2, 1], from_round = 3 }]\n", "overlap"),
        ("[faults]\nnetem = [{ link = [1, 2], from_round = 1, loss = 1.5 }]\n", "loss"),
        ("[faults]\nnetem = [{ link = [1, 2], from_round = 1 }]\n", "delay_ms, loss and/or rate_mbit"),
        ("[faults]\nnetem = [{ link = [1, 2], from_round = 1, delay_ms = 5, jitter_ms = 9 }]\n", "jitter"),
        ("[faults]\nkil = []\n", "kil"),
        ("[run]\nmode = 'docker'\n", "docker"),
        ("[daemon]\nsummary_width = 4\n", "summary_width"),
    ],
)
def test_bad_scenarios_name_the_problem(tmp_path, extra, needle):
    assert needle in error(tmp_path, extra)


def test_topology_errors(tmp_path):
    assert "ring needs at least 3" in error(tmp_path, base=BASE.replace('robots = 3', 'robots = 2').replace('"line"', '"ring"'))
    assert "hub" in error(tmp_path, base=BASE.replace('kind = "line"', 'kind = "star"\nhub = 9'))
    assert "edge" in error(tmp_path, base=BASE.replace('kind = "line"', 'kind = "edges"\nedges = [[1, 4]]'))


def test_missing_file_table_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_scenario(tmp_path / "nope.toml")
    assert "[scenario]" in error(tmp_path, base="[split]\noverlap = 0.1\n")
    assert "not valid TOML" in error(tmp_path, base="[scenario\nname=1")


def test_missing_dataset_is_clear(tmp_path):
    s = load_scenario(write(tmp_path, base=BASE.replace('"procedural:views=30,width=32"', '"no/such/data"')))
    with pytest.raises(FileNotFoundError, match="no/such/data"):
        s.resolved_dataset()
    assert resolve_dataset("procedural:views=3") == "procedural:views=3"


def test_find_scenario_by_name_and_path(tmp_path):
    p = write(tmp_path)
    assert find_scenario(str(p)) == p
    assert find_scenario(str(tmp_path)) == tmp_path / "scenario.toml"
    with pytest.raises(FileNotFoundError, match="no scenario 'nope'"):
        find_scenario("nope")


def test_shipped_scenarios_are_valid():
    """Every scenarios/*/scenario.toml loads, and its name is its folder's."""
    found = list_scenarios()
    assert found, "no scenarios shipped"
    for folder in found:
        s = load_scenario(folder)
        assert s.name == folder.name
        if s.faults.needs_netns:
            assert s.run.mode == "netns", f"{folder.name}: link faults need run.mode = netns"


@pytest.mark.parametrize("extra, known", [
    ('[split]\nframe = "world"\n', True),  # shared frames, the pose fixed at the identity
    ('[split]\nframe = "world"\n[training.train.pose]\nmode = "se3"\n', False),  # learnt: its error is measured
    ('[split]\nframe = "offset"\n', False),  # local frames: a coarse start, then learnt
])
def test_pose_panels_only_where_the_pose_is_measured(tmp_path, extra, known):
    from cli.scenario.figures import poses_known

    assert poses_known(load_scenario(write(tmp_path, extra))) is known
    assert "orbit_frames" in error(tmp_path, "[report]\norbit_frames = -1\n")


def test_replayed_and_reversed_recordings_need_recordings_and_known_robots(tmp_path):
    assert "need record.enabled" in error(tmp_path, "[record]\nreplay = true\n")
    assert "record.reverse: [7] not among the robots" in error(tmp_path, "[record]\nenabled = true\nreverse = [7]\n")
    assert "replay_pace must be > 0" in error(tmp_path, "[record]\nenabled = true\nreplay = true\nreplay_pace = 0\n")
    s = load_scenario(write(tmp_path, "[record]\nenabled = true\nreplay = true\nreverse = [2]\n"))
    assert s.record.replay and s.record.reverse == [2]
