"""The daemon's round logic in one process, over the in-memory network (protocol.loopback).

Real daemons, real trainer, real codec; only the sockets are gone. That makes the round logic
cheap to test exactly: a line of three must end bit-identical to the in-process simulation,
as it does over Zenoh (tests/system/test_daemon.py).
"""

from __future__ import annotations

import threading

import pytest
import torch

from agent.checkpoint import RunFolder
from agent.daemon import Daemon, DaemonConfig, SwarmIdentity
from agent.data.folder import read_scene
from agent.data.loaders import load_views
from agent.telemetry import read_telemetry
from cli.config import from_dict
from protocol.keys import Keys
from protocol.loopback import LoopbackHub, LoopbackNetwork, key_matches
from tests.system.harness import make_swarm, simulate

pytestmark = pytest.mark.slow


def test_key_expressions_match_as_in_zenoh():
    assert key_matches("dinerf/s/theta/1/*/2", "dinerf/s/theta/1/17/2")
    assert not key_matches("dinerf/s/theta/1/*/2", "dinerf/s/theta/1/17/3")
    assert not key_matches("dinerf/s/theta/*", "dinerf/s/theta/1/17/2")
    assert key_matches("dinerf/s/**", "dinerf/s/theta/1/17/2") and key_matches("dinerf/**", "dinerf")


def run_in_process(swarm, training_cfg, daemon_cfg, links=None, warn=None, hostile: dict[int, str] | None = None
                   ) -> dict[int, Daemon]:
    """Every robot of ``swarm`` as a Daemon thread on one LoopbackHub; returns them when all are done.
    ``hostile``: robot -> an attack of tests/system/hostile.py for that robot."""
    from tests.system.hostile import install
    from cli.swarm_file import load_swarm_file

    cfg, base = load_swarm_file(swarm.swarm_file)
    topo = cfg.graph()
    hub = LoopbackHub(links=links if links is not None else topo.edges)
    scene = read_scene(base / cfg.swarm.scene)
    daemons, nets, errors = {}, [], []
    for i in cfg.swarm.robots:
        net = LoopbackNetwork(hub, Keys(cfg.swarm.name), i).open()
        nets.append(net)
        daemons[i] = Daemon(i, load_views(swarm.root / f"robot{i}"), scene.box_from_shared,
                            SwarmIdentity(cfg.swarm.name, topo), training_cfg or cfg.training,
                            daemon_cfg or cfg.daemon, net, swarm.run_dir(i), log=lambda line: None, warn=warn)
        if i in (hostile or {}):
            install(hostile[i].split("+"), robot=daemons[i])

    def run(d: Daemon) -> None:
        try:
            d.run()
        except Exception as e:  # surfaced below, in the test's thread
            errors.append(e)

    threads = [threading.Thread(target=run, args=(d,)) for d in daemons.values()]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    for net in nets:
        net.close()
    assert not errors, errors
    assert not any(t.is_alive() for t in threads), "a daemon did not finish"
    return daemons


QUICK = {"startup_wait_s": 5.0, "round_timeout_s": 30.0, "initial_pose": "identity", "linger_s": 0.2, "threads": 1}


def _as_simulated(swarm, sim, i: int) -> list:
    """Robot i's records, after checking that its field is the simulation's, bit for bit."""
    ck = RunFolder(swarm.run_dir(i), create=False).load()
    mine = sim.robots[i].trainer.field.state_dict()
    assert all(torch.equal(mine[k], ck.trainer["field"][k]) for k in mine), f"robot {i} differs from the simulation"
    records = read_telemetry(RunFolder(swarm.run_dir(i)).telemetry)
    assert [r.round for r in records] == [1, 2, 3, 4, 5]
    return records


def test_a_line_of_three_in_one_process_matches_the_simulation(tmp_path):
    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=3, topology="line")
    run_in_process(swarm, None, from_dict(DaemonConfig, QUICK))
    sim = simulate(swarm)
    for i in swarm.robots:
        records = _as_simulated(swarm, sim, i)
        line = {1: [2], 2: [1, 3], 3: [2]}[i]
        assert all(r.heard == line for r in records), records
        # A neighbour a round ahead may land in the round before (the windows are by time), but
        # every neighbour's bytes are counted and only neighbours send.
        received = {j: sum(r.bytes_in.get(j, 0) for r in records) for j in line}
        assert all(received.values()) and all(set(r.bytes_in) <= set(line) for r in records), records


def test_a_robot_that_hears_no_neighbour_for_three_rounds_says_so_once(tmp_path):
    """Two robots whose link is down (a link too slow for any snapshot looked just like this: robots
    training alone, heard [] on every log line, and nothing else said) warn once, at the third
    round without a snapshot, with an event."""
    from agent.telemetry import read_events

    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=2, topology="full", training={"rounds": 5, "steps_per_round": 2})
    warnings: list[str] = []
    cfg = from_dict(DaemonConfig, {"startup_wait_s": 0.5, "round_timeout_s": 1.0, "initial_pose": "identity",
                                   "linger_s": 0.2, "threads": 1, "silent_after_s": 1.0, "heartbeat_s": 0.2})
    run_in_process(swarm, None, cfg, links=[], warn=warnings.append)
    for i in swarm.robots:
        assert all(r.heard == [] for r in read_telemetry(RunFolder(swarm.run_dir(i)).telemetry))
        isolated = [e for e in read_events(RunFolder(swarm.run_dir(i)).events) if e["event"] == "isolated"]
        assert len(isolated) == 1 and isolated[0]["round"] == 3, isolated
    said = [w for w in warnings if "heard none of its neighbours" in w]
    assert sorted(w.split("]")[0] for w in said) == ["[robot 1", "[robot 2"], warnings
    assert all("delta+uniform" in w and "MB at float32" in w for w in said), said


def test_a_field_set_against_what_the_images_show_is_said_at_start(tmp_path):
    """The split sized the box for a bounded field (these images have alpha); a robot told to train
    an unbounded one in it says so before its first round, in one line."""
    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=2, topology="full",
                       training={"rounds": 1, "steps_per_round": 1, "train": {"field": {"unbounded": True}}})
    warnings: list[str] = []
    cfg = from_dict(DaemonConfig, {"startup_wait_s": 2.0, "round_timeout_s": 5.0, "initial_pose": "identity",
                                   "linger_s": 0.2, "threads": 1})
    run_in_process(swarm, None, cfg, warn=warnings.append)
    said = [w for w in warnings if "unbounded = true" in w]
    assert sorted(w.split("]")[0] for w in said) == ["[robot 1", "[robot 2"], warnings
    assert all("\n" not in w and "floaters" in w for w in said)


def test_a_loss_that_stays_flat_and_high_is_said_once(tmp_path):
    """A field that learns nothing (learning rate ~0 here; a bounded box around a room in real life)
    used to go flat silently; the daemon warns once, with an event."""
    from agent.telemetry import read_events

    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=2, topology="full",
                       training={"rounds": 6, "steps_per_round": 2, "train": {"optim": {"lr": 1e-12}}})
    warnings: list[str] = []
    cfg = from_dict(DaemonConfig, {"startup_wait_s": 5.0, "round_timeout_s": 30.0, "initial_pose": "identity",
                                   "linger_s": 0.2, "threads": 1, "plateau": {"window": 3, "rel_change": 0.5}})
    run_in_process(swarm, None, cfg, warn=warnings.append)
    for i in swarm.robots:
        flat = [e for e in read_events(RunFolder(swarm.run_dir(i)).events) if e["event"] == "loss_flat"]
        assert len(flat) == 1 and flat[0]["round"] == 3 and flat[0]["rgb_loss"] > 0.02, flat
    said = [w for w in warnings if "the training loss has been flat" in w]
    assert sorted(w.split("]")[0] for w in said) == ["[robot 1", "[robot 2"], warnings


# The daemon's path is the same for every mode (the codes have unit tests); a few-level mode also
# checks that the daemons run C-ADMM on their own snapshot as received, as the simulation does.
@pytest.mark.parametrize("mode", ["delta+topk", "delta+quinary", "delta+uniform"])
def test_a_compressed_line_of_three_hears_everyone_at_a_fraction_of_the_bytes(tmp_path, mode):
    """The daemons' own path with compression on: every round every neighbour's delta arrives and
    resolves against theta^0 and then the previous round (no full snapshot after the seed), at a
    fraction of float32; each robot ends holding exactly its neighbours' public copies, and with the
    same models as the in-process simulation through the same wire."""
    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=3, topology="line")
    cfg = from_dict(DaemonConfig, {"startup_wait_s": 5.0, "round_timeout_s": 30.0, "initial_pose": "identity",
                                   "linger_s": 0.2, "threads": 1,
                                   "exchange": {"compression": mode, "topk_fraction": 0.05}})
    daemons = run_in_process(swarm, None, cfg)
    sim = simulate(swarm, compression=cfg.exchange)
    limit = 0.1 if mode == "delta+topk" else 0.4
    for i in swarm.robots:
        records = read_telemetry(RunFolder(swarm.run_dir(i)).telemetry)
        line = {1: [2], 2: [1, 3], 3: [2]}[i]
        assert [r.round for r in records] == [1, 2, 3, 4, 5] and all(r.heard == line for r in records), records
        assert all(sorted(r.bytes_out_links) == line for r in records)
        assert all(r.wire_ratio is not None and r.wire_ratio < limit for r in records), [r.wire_ratio for r in records]
        assert "base_missing" not in daemons[i].folder.events.read_text()
        for j in line:  # what i holds of j is j's public copy, bit for bit (the digest says so)
            assert daemons[i].exchange.bases.held(j) == daemons[j].exchange.encoder.public() != None
        # the simulation through the same encode/decode (ProtocolWire) ends where the daemons do, bit for bit
        ck = RunFolder(swarm.run_dir(i), create=False).load().trainer["field"]
        mine = sim.robots[i].trainer.field.state_dict()
        assert all(torch.equal(mine[k], ck[k]) for k in mine), f"robot {i} differs from the compressed simulation"
        print(f"{mode} robot {i}: wire ratio {[round(r.wire_ratio, 4) for r in records]}, push bytes in the "
              f"simulation {sim.wire.sent[i]}")


def test_a_forged_far_future_reply_to_the_join_never_becomes_a_neighbours_base(tmp_path):
    """Robot 3 trains and pushes honestly, but claims the last round from the start and answers
    every ``latest`` query with a forged model of it (tests/system/hostile.py ``future``). The
    join asks for nothing past the quorum of the claims, so the forgery never becomes robot 3's
    base at the others (it did, and none of robot 3's real deltas fitted it: every barrier waited
    out the round timeout), and nobody moves to its round: all three end bit-identical to the
    honest simulation, robot 3 included, having waited less than a second in any round."""
    torch.set_num_threads(1)
    swarm = make_swarm(tmp_path, robots=3, topology="full")
    run_in_process(swarm, None, from_dict(DaemonConfig, QUICK), hostile={3: "future"})
    sim = simulate(swarm)
    for i in swarm.robots:
        records = _as_simulated(swarm, sim, i)
        assert max(r.seconds_wait for r in records) < 1.0, records
