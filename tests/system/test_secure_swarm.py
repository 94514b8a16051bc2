"""A secure swarm end to end: real `dinerf-agent up` robots over mutual TLS with access control,
an impostor holding robot 2's valid certificate, and `dinerf-agent status` with the monitor's."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import pytest

from tests.system.harness import REPO, free_port_base, make_swarm, simulate
from tests.system.test_daemon import _field_equal

pytestmark = pytest.mark.slow


def test_a_valid_certificate_cannot_speak_for_another_robot_and_status_sees_the_tls_swarm(tmp_path):
    """The impostor (robot 2's certificate, so its link is admitted) offers robot 1's latest queryable
    (answering round 1,000,000) and sends future copies and altered replays of robot 1's snapshots
    to robot 2. Robot 2's access control drops the queryable's declaration, so no query ever
    reaches it, and the puts before any callback: no refusal is even counted, and both robots end
    bit-identical to the clean run. Meanwhile `status` (monitor certificate) sees both robots."""
    from cli.swarm_file import load_swarm_file

    swarm = make_swarm(tmp_path, robots=2, topology="full", training={"rounds": 4}, secure=True)
    cfg, _ = load_swarm_file(swarm.swarm_file)
    impostor_ep = f"tls/127.0.0.1:{free_port_base(1) + 1}"
    impostor = subprocess.Popen([sys.executable, str(REPO / "tests/system/hijack.py"), str(swarm.swarm_file), "90",
                                 impostor_ep, str(swarm.root / "robot2" / "tls")],
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert impostor.stdout.readline().strip() == "ready", impostor.stdout.read()
        for i, j in ((1, 2), (2, 1)):  # each robot dials its neighbour and, unknowingly, the impostor
            swarm.start(i, extra_args=["--connect", cfg.endpoint(j), "--connect", impostor_ep])
        status = subprocess.Popen([sys.executable, "-m", "cli", "status", "--swarm", str(swarm.swarm_file), "--once", "6"],
                                  cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  env=dict(os.environ, COLUMNS="200"))
        status_out, status_err = status.communicate(timeout=60)
        swarm.wait_all()
    finally:
        impostor.kill()
        impostor_out = impostor.communicate()[0]
        swarm.stop()
    assert status.returncode == 0, status_err
    rows = {int(m[1]) for m in re.finditer(r"^│\s+(\d+)\s+│\s+(\d+)\s+│", status_out, re.M)}
    assert rows == {1, 2}, status_out
    assert "secure: mutual TLS as robot-1" in swarm.log_text(1)
    sent = json.loads([line for line in impostor_out.splitlines() if line.startswith('{"latest')][-1])
    print(f"the impostor sent {sent}")
    assert sent["linked"] and sent["future_copies"] > 0 and sent["replays"] > 0, sent
    assert sent["latest_answers"] == 0, sent  # an insecure swarm asks it (test_daemon's hijack test)
    refused = {i: swarm.done(i)["rejected"] for i in swarm.robots}
    print(f"refused by reason: {refused}")  # the forgeries never reached the codec
    assert not any(r.get("ahead_of_sender") or r.get("too_far_ahead") for r in refused.values()), refused
    sim = simulate(swarm)
    for i in swarm.robots:
        tel = swarm.telemetry(i)
        assert [t.round for t in tel] == [1, 2, 3, 4] and all(t.steps == 8 for t in tel), (i, tel)
        exact, diff = _field_equal(sim.robots[i].trainer, swarm.run_dir(i))
        assert exact, f"robot {i}: the impostor changed theta (max diff {diff:.3e})"
