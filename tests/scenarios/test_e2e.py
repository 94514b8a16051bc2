"""End to end: `scenario run` machinery with the real `dinerf-agent up` daemons, in network namespaces.

Each test runs a tiny swarm (24x24 procedural scene, 2^12 hash table, a few steps per round), applies
one fault on the real network, and asserts what the survivors achieved: every round done, the
fault seen where it should be (who was heard), checkpoints intact, and image quality next to the
same swarm without the fault. Needs root (skipped otherwise, with the reason).

The 24x24 images are point-sampled (``supersample=1``): the PSNR tolerances below were set on
them. With anti-aliased images the models reach ~20 dB instead of ~16 and, when the healed
link came back only ~5 s after the heal (before the transport fixes), the cut cost robot 2
1.7-2.0 dB instead of 0.2-0.5.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from agent.checkpoint import CHECKPOINT
from agent.telemetry import RoundRecord, read_telemetry
from cli.scenario.compare import rounds_lost_per_restart
from cli.scenario.netns import list_namespaces
from cli.scenario.report import build_report
from cli.scenario.runner import ScenarioRunner
from cli.scenario.spec import load_scenario
from tests.scenarios.netns_helpers import needs_netns

pytestmark = [needs_netns, pytest.mark.netns, pytest.mark.slow]

TINY = """
[scenario]
name = "e2e"
dataset = "procedural:views=36,width=24,supersample=1"
robots = 4
[split]
overlap = 0.2
frame = "world"
test_every = 6
[topology]
kind = "ring"
[training]
rounds = ROUNDS
steps_per_round = 8
seed = 3
own_holdout_every = 0
[training.train]
rays_per_step = 256
[training.train.field]
density_hidden = 32
color_hidden = 32
[training.train.field.grid]
log2_hashmap_size = 12
num_levels = 8
max_resolution = 128
[training.train.occupancy]
resolution = 32
warmup_steps = 16
update_every = 8
[network]
lease_ms = 1000
[daemon]
round_timeout_s = 20
startup_wait_s = 20
eval_every = 0
[report]
eval_every = 100
render_views = 2
ssim = false
workers = 1
[run]
mode = "netns"
timeout_s = 240
"""


ROUNDS = 8
CUT_ROUNDS = 12


def events_of(out: Path, robot: int) -> list[dict]:
    return [json.loads(line) for line in (out / f"robots/{robot}/events.jsonl").read_text().splitlines()]


def run_scenario(tmp: Path, name: str, faults: str = "", steps: int = 8, rounds: int = ROUNDS, daemon: str = ""):
    folder = tmp / name
    folder.mkdir()
    text = TINY.replace("ROUNDS", str(rounds)).replace("steps_per_round = 8", f"steps_per_round = {steps}")
    text = text.replace("[daemon]\n", f"[daemon]\n{daemon}")
    (folder / "scenario.toml").write_text(text + faults)
    spec = load_scenario(folder)
    out = folder / "out"
    runner = ScenarioRunner(spec, out, echo=lambda s: None)
    outcome = runner.run()
    assert not [n for n in list_namespaces() if n.startswith(runner.lab.run_id)], "namespaces left behind"
    report = build_report(out, echo=lambda s: None) if outcome.ok else None
    return outcome, out, report


def telemetry(out: Path, robot: int) -> list[RoundRecord]:
    return read_telemetry(out / "robots" / str(robot) / "telemetry.jsonl")


@pytest.fixture(scope="module")
def fault_free(tmp_path_factory):
    outcome, out, report = run_scenario(tmp_path_factory.mktemp("free"), "free")
    assert outcome.ok, outcome.reason
    return out, report


def final_psnr(report: dict, robot: int) -> float:
    return report["robots"][str(robot)]["final"]["psnr"]


def test_fault_free_swarm_completes(fault_free):
    out, report = fault_free
    for i in (1, 2, 3, 4):
        recs = telemetry(out, i)
        assert [r.round for r in recs] == list(range(1, ROUNDS + 1))
        assert json.loads((out / f"robots/{i}/done.json").read_text())["rounds"] == ROUNDS
        assert all(r.heard == r.live_neighbours for r in recs)
        assert math.isfinite(final_psnr(report, i))
    assert (out / "report.md").is_file() and (out / "convergence.png").is_file() and (out / "renders.png").is_file()


def test_scoring_in_worker_processes_gives_the_same_scores(fault_free):
    """The report scores the rounds in 2 processes by default: the same figures as here, to the bit."""
    from agent.evaluation import ScoringOptions, score_run
    from cli.scenario.report import load_run_spec, swarm_run

    out, report = fault_free
    spec = load_run_spec(out)
    run = swarm_run(out, spec.ids)
    opts = ScoringOptions(every=3, with_ssim=False, own_views_every=spec.report.own_views_every)
    here, two = score_run(run, opts), score_run(run, opts, workers=2)
    assert len(here.rounds[1]) >= 3 and sorted(two.finals) == sorted(here.finals) == spec.ids
    for i in spec.ids:
        assert list(two.rounds[i]) == list(here.rounds[i])
        assert [r.to_dict() for r in two.rounds[i].values()] == [r.to_dict() for r in here.rounds[i].values()]
    assert two.final(1).psnr == report["robots"]["1"]["final"]["psnr"]


def test_kill_a_robot_survivors_finish(tmp_path, fault_free):
    """SIGKILL robot 3 of the ring 1-2-3-4 at round 2: the others finish every round, near the fault-free run."""
    outcome, out, report = run_scenario(tmp_path, "kill", "[faults]\nkill = [{ robot = 3, round = 2 }]\n")
    assert outcome.ok, outcome.reason
    run = json.loads((out / "run.json").read_text())
    kill = next(e for e in run["events"] if e.get("fault") == "kill")
    assert run["robots"]["3"]["exit_codes"] == [-9]
    for i, other in ((2, 1), (4, 1)):
        recs = telemetry(out, i)
        assert [r.round for r in recs] == list(range(1, ROUNDS + 1))
        late = [r for r in recs if r.round >= kill["robot_rounds"][str(i)] + 2]  # begun after the kill
        assert late and all(r.live_neighbours == [other] and r.heard == [other] for r in late), late
        # liveliness notices the death: nobody waits out the 20 s barrier for the dead robot
        assert all(r.seconds_wait < 10 for r in late), [r.seconds_wait for r in late]
    for i in (1, 2, 4):
        assert (out / f"robots/{i}/done.json").is_file()
        assert abs(final_psnr(report, i) - final_psnr(fault_free[1], i)) < 1.0
    # the dead robot's checkpoint is intact and loadable (no lost checkpoint)
    from agent.checkpoint import load_for_eval

    trainer = load_for_eval(out / "robots/3", out / "data/robot3")
    assert trainer.step == 8 * len(telemetry(out, 3))


CUT_STEPS = 32


@pytest.fixture(scope="module")
def fault_free_long(tmp_path_factory):
    """The fault-free run with the cut run's rounds and steps, to compare PSNR against."""
    outcome, out, report = run_scenario(tmp_path_factory.mktemp("free-long"), "free", steps=CUT_STEPS, rounds=CUT_ROUNDS)
    assert outcome.ok, outcome.reason
    return out, report


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory):
    """Cut 2-3 of the ring 1-2-3-4 from round 2 to round 5, then run on long enough (~1 s rounds)
    for the Zenoh session over the healed link to come back (reconnect back-off <= 2 s)."""
    outcome, out, report = run_scenario(tmp_path_factory.mktemp("cut"), "cut",
                                        "[faults]\ncut = [{ link = [2, 3], from_round = 2, to_round = 5 }]\n",
                                        steps=CUT_STEPS, rounds=CUT_ROUNDS)
    assert outcome.ok, outcome.reason
    run = json.loads((out / "run.json").read_text())
    cut = next(e for e in run["events"] if e.get("fault") == "cut")
    heal = next(e for e in run["events"] if e.get("fault") == "heal")
    return out, report, cut, heal


def test_cut_link_is_silent_while_cut_and_everyone_finishes(cut_run, fault_free_long):
    out, report, cut, heal = cut_run  # noqa: RUF059
    for i, peer, other in ((2, 3, 1), (3, 2, 4)):
        recs = {r.round: r for r in telemetry(out, i)}
        assert max(recs) == CUT_ROUNDS and (out / f"robots/{i}/done.json").is_file()
        inside = [k for k in recs if cut["robot_rounds"][str(i)] + 1 < k <= heal["robot_rounds"][str(i)]]
        assert inside, recs.keys()
        # the cut link carries nothing (the peer may still count as alive: liveness is gossiped around
        # the ring) ...
        assert all(peer not in recs[k].heard for k in inside), {k: recs[k].heard for k in recs}
        # ... and the other link carries every round: the cut no longer stalls the healthy links
        # (ZenohTransport: BLOCK wait below the lease, receive threads for lingering closes)
        assert all(recs[k].heard == [other] for k in inside), {k: recs[k].heard for k in recs}
    # Quality next to the fault-free run: the swarm's mean closely, each robot loosely. The healed
    # link is used again 1-2 rounds after the heal, so in this 12-round run the cut lasts about
    # 5 rounds (before the transport fixes up to 8; robot 2 then ended 0.2-1.1 dB below, 7 runs).
    diffs = [final_psnr(report, i) - final_psnr(fault_free_long[1], i) for i in (1, 2, 3, 4)]
    assert abs(sum(diffs) / 4) < 0.75 and all(abs(d) < 2.0 for d in diffs), diffs


def test_after_the_heal_the_swarm_is_in_step_again(cut_run):
    out, _report, _cut, heal = cut_run
    for i, peer in ((2, 3), (3, 2)):
        recs = {r.round: r for r in telemetry(out, i)}
        after = [k for k in recs if k > heal["robot_rounds"][str(i)] + 1]
        assert after and all(peer in recs[k].live_neighbours for k in after)  # healed: alive again
        # the healed link carries the snapshots again within two rounds (1-2 in 8 runs), then always
        assert all(peer in recs[k].heard for k in after[1:]), {k: recs[k].heard for k in recs}
    for i in (1, 2, 3, 4):
        recs = telemetry(out, i)
        assert [r.round for r in recs] == list(range(1, CUT_ROUNDS + 1)), "rounds skipped"
        # No round waits long: before the transport fixes every cut cost a 5 s stall and most an
        # 8-10 s one (lingering socket closes); now the longest wait in 8 runs was 0.73 s. 5 s
        # leaves room for one lost push and its pull, or for a token that outlives its link (the
        # barrier gives up on a neighbour silent for daemon.silent_after_s, 3 s).
        assert all(r.seconds_wait < 5 for r in recs), [r.seconds_wait for r in recs]


def test_a_frozen_robot_comes_back_in_step(tmp_path, fault_free_long):
    """SIGSTOP robot 3 at round 2 until the others are 3 rounds further (its lease expires; 2 and 4
    go on without it), then SIGCONT.

    It wakes up rounds behind, with neighbours too far ahead to buffer their snapshots (a window
    of one round here): it must learn where they are and catch up, not wait at every barrier for
    rounds they left long ago (which cost 20 s per round, for the rest of the run, before the
    mailbox kept a sender's newest snapshot beyond the window). The freeze is counted in the
    others' rounds: a freeze in seconds left it only one round behind on a fast machine.
    """
    outcome, out, report = run_scenario(tmp_path, "freeze",
                                        "[faults]\nfreeze = [{ robot = 3, round = 2, rounds = 3, seconds = 120 }]\n",
                                        steps=CUT_STEPS, rounds=CUT_ROUNDS, daemon="max_ahead = 1\n")
    assert outcome.ok, outcome.reason
    run = json.loads((out / "run.json").read_text())
    thaw = next(e for e in run["events"] if e.get("fault") == "thaw")
    frozen_at = thaw["robot_rounds"]["3"]
    assert all(thaw["robot_rounds"][str(i)] >= frozen_at + 3 for i in (2, 4)), thaw  # thawed by rounds, not time
    for i in (1, 2, 3, 4):
        recs = telemetry(out, i)
        assert recs[-1].round == CUT_ROUNDS and (out / f"robots/{i}/done.json").is_file()
        # Not out of phase: at most one barrier runs into its 20 s deadline per robot (the old
        # mailbox made it every round). One can: in ~1 run of 6 the thawed robot's Zenoh link
        # to a neighbour comes back one-sided (it sees the neighbour's token, the neighbour does
        # not see its), so it waits for a snapshot that is not sent; a known limitation.
        waits = [(r.round, round(r.seconds_wait, 1)) for r in recs]
        assert sum(w >= 10 for _, w in waits) <= 1, waits
    after = [r for r in telemetry(out, 3) if r.round > thaw["robot_rounds"]["3"] + 1]
    assert after and any(r.heard == [2, 4] for r in after), [(r.round, r.heard) for r in telemetry(out, 3)]
    caught = [e for e in events_of(out, 3) if e["event"] in ("caught_up", "training_through")]
    assert caught, "robot 3 never noticed that its neighbours were ahead"
    for i in (1, 2, 4):
        assert abs(final_psnr(report, i) - final_psnr(fault_free_long[1], i)) < 1.0


def test_killed_robot_restarts_and_resumes(tmp_path, fault_free):
    """SIGKILL robot 3 at round 2, start it again at round 3: it resumes from its checkpoint and finishes.

    Longer rounds here (40 steps) and more of them: a restart takes 5-10 s under load (imports,
    Zenoh), and the swarm must still be running when the robot is back (if it is not, the robot
    adopts the finished swarm's round and trains nothing more, which is right but proves nothing).
    """
    rounds = 14
    outcome, out, report = run_scenario(tmp_path, "restart",
                                        "[faults]\nkill = [{ robot = 3, round = 2 }]\nrestart = [{ robot = 3, round = 3 }]\n",
                                        steps=40, rounds=rounds)
    assert outcome.ok, outcome.reason
    run = json.loads((out / "run.json").read_text())
    assert run["robots"]["3"]["starts"] == 2 and run["robots"]["3"]["exit_codes"][0] == -9
    kill = next(e for e in run["events"] if e.get("fault") == "kill")
    log = (out / "logs/robot3.log").read_text()
    assert f"resumed from {out / 'robots/3' / CHECKPOINT} at round" in log
    recs = telemetry(out, 3)
    done = [r.round for r in recs]
    assert done == sorted(set(done)) and done[-1] == rounds  # no round twice, finished
    assert len(done) > kill["robot_rounds"]["3"], done  # trained after the restart
    done_before = kill["robot_rounds"]["3"]
    assert done[:done_before] == list(range(1, done_before + 1))  # nothing of before the kill lost
    assert rounds_lost_per_restart(out / "robots/3") == [0]  # the checkpoint had every completed round
    assert any(3 in r.heard for r in telemetry(out, 4) if r.round >= done[done_before])  # back in the swarm
    for i in (1, 2, 4):  # same steps per round as the fault-free run only for the survivors' schedule: loose
        assert math.isfinite(final_psnr(report, i))


def test_lossy_slow_link_still_carries_the_model(tmp_path, fault_free):
    """10% loss and 100 ms each way on link 1-2 from round 1: snapshots still cross it, everyone finishes."""
    outcome, out, report = run_scenario(tmp_path, "lossy",
                                        "[faults]\nnetem = [{ link = [1, 2], from_round = 1, delay_ms = 100, loss = 0.1 }]\n")
    assert outcome.ok, outcome.reason
    run = json.loads((out / "run.json").read_text())
    netem = next(e for e in run["events"] if e.get("fault") == "netem")
    for i, peer in ((1, 2), (2, 1)):
        recs = {r.round: r for r in telemetry(out, i)}
        late = [k for k in recs if k > netem["robot_rounds"][str(i)] + 1]
        assert late and max(recs) == ROUNDS and (out / f"robots/{i}/done.json").is_file()
        # the snapshots (the default code, 15-35 KB; after a lost one the deltas since) still cross
        # the link at ~30 KB/s of TCP goodput at this loss and delay, and are used. Not in every
        # round: at 10% loss the link can flap (liveliness lost), the barriers go on without that
        # neighbour meanwhile, by design, and the delta pushed when it is back finds no base, so a
        # full pull (~0.27 MB, ~9 s here) follows. Locally 8 of 8 runs heard every late round; a CI
        # run heard 3 of 6 after one such flap (base_missing, then pulled). Bytes count in the round
        # they arrive, which may be the one before
        assert sum(recs[k].bytes_in.get(peer, 0) for k in late) > 50_000, {k: recs[k].bytes_in for k in recs}
        seen = {k: (recs[k].heard, round(recs[k].seconds_wait, 1)) for k in recs}
        notes = [e for e in events_of(out, i) if e["event"] in ("silent", "pulled", "base_missing")]
        assert 2 * sum(peer in recs[k].heard for k in late) >= len(late), (seen, notes)
    relay_log = out / "logs/relay-1-2.log"
    if relay_log.is_file():  # the userspace emulator (no sch_netem here): it really dropped packets ...
        events = [json.loads(l) for l in relay_log.read_text().splitlines() if l.startswith("{")]
        final, at_set = events[-1], [e for e in events if e["event"] == "set"][-1]
        assert final["loss"] == 0.1 and sum(final[d]["dropped"] for d in ("to1->to2", "to2->to1")) > 0
        # ... and the snapshots themselves went through it (not through Zenoh's shared memory)
        crossed = final["to1->to2"]["bytes"] - at_set["to1->to2"]["bytes"]
        received = sum(r.bytes_in.get(1, 0) for r in telemetry(out, 2) if r.round > netem["robot_rounds"]["2"] + 1)
        assert crossed >= 0.9 * received > 0, (crossed, received)
    for i in (1, 2, 3, 4):
        assert abs(final_psnr(report, i) - final_psnr(fault_free[1], i)) < 1.0
