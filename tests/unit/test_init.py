"""`dinerf-agent init`: a swarm for robots with their own recordings, and `cert issue` adding one to it."""

from __future__ import annotations

from typer.testing import CliRunner

import cli.main
from cli.swarm_file import load_swarm_file
from protocol.pki import check_identity

cli.main._register()
runner = CliRunner()


def test_init_writes_the_ca_apart_a_certificate_per_robot_and_a_swarm_file_without_a_scene(tmp_path):
    out = tmp_path / "fleet"
    res = runner.invoke(cli.main.app, ["init", "--robots", "1,2", "--robot", "3=10.0.0.13", "--robot",
                                       "4=rover4.lan:9000", "--out", str(out), "--topology", "ring", "--rounds", "7"])
    assert res.exit_code == 0, res.output
    cfg, _ = load_swarm_file(out / "swarm.toml")
    assert cfg.swarm.frames == "local" and cfg.swarm.scene == "" and cfg.training.rounds == 7
    assert cfg.training.train.pose.mode == "se3" and cfg.daemon.initial_pose == "coarse"
    assert cfg.network.endpoints == {"1": "tls/127.0.0.1:7501", "2": "tls/127.0.0.1:7502",
                                     "3": "tls/10.0.0.13:7503", "4": "tls/rover4.lan:9000"}
    for i in (1, 2, 3, 4):
        check_identity(out / f"robot{i}" / "tls", f"robot-{i}")
        assert not (out / f"robot{i}" / "tls" / "ca.key").exists()  # the CA's key stays with the operator
        assert f"dinerf-agent up --id {i} --data <its recording> --swarm swarm.toml --tls tls" in res.output
    check_identity(out / "monitor", "monitor")
    assert (out / "ca" / "ca.key").is_file()
    again = runner.invoke(cli.main.app, ["init", "--robots", "1", "--out", str(out)])
    assert again.exit_code == 2 and "exists" in again.stderr
    for bad in (["--robot", "x=host"], ["--robot", "3=host:port"], ["--robots", "1,a"], []):
        res = runner.invoke(cli.main.app, ["init", "--out", str(tmp_path / "bad"), *bad])
        assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, (bad, res.stderr)


def test_cert_issue_on_an_initialised_swarm_adds_the_robot_to_its_roster(tmp_path):
    out = tmp_path / "fleet"
    assert runner.invoke(cli.main.app, ["init", "--robots", "1,2", "--out", str(out)]).exit_code == 0
    res = runner.invoke(cli.main.app, ["cert", "issue", "--swarm", str(out / "swarm.toml"), "--id", "3"])
    assert res.exit_code == 0, res.output
    cfg, _ = load_swarm_file(out / "swarm.toml")
    assert cfg.swarm.robots == [1, 2, 3] and cfg.network.endpoints["3"] == "tls/127.0.0.1:7503"
    check_identity(out / "robot3" / "tls", "robot-3")
    mixed = tmp_path / "mixed"
    assert runner.invoke(cli.main.app, ["init", "--robot", "1=a.lan", "--robot", "2=b.lan:7000",
                                        "--out", str(mixed)]).exit_code == 0
    res = runner.invoke(cli.main.app, ["cert", "issue", "--swarm", str(mixed / "swarm.toml"), "--id", "3"])
    assert res.exit_code == 2 and "--host" in res.stderr and not (mixed / "robot3").exists()
    res = runner.invoke(cli.main.app, ["cert", "issue", "--swarm", str(mixed / "swarm.toml"), "--id", "3",
                                       "--host", "c.lan", "--port", "7003"])
    assert res.exit_code == 0 and load_swarm_file(mixed / "swarm.toml")[0].network.endpoints["3"] == "tls/c.lan:7003"
