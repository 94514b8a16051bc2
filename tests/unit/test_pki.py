"""The swarm PKI (protocol.pki), the access control it feeds (protocol.acl) and the swarm file's
[security] section: secure unless said otherwise, and said loudly."""

from __future__ import annotations

import json
import stat

import pytest

from cli.config import ConfigError
from cli.swarm_file import loopback_endpoints, security_sections, swarm_doc, write_swarm_file, load_swarm_file
from protocol import pki
from protocol.acl import access_control
from protocol.keys import Keys
from protocol.transport import TransportConfig


@pytest.fixture(scope="module")
def swarm_pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("swarm")
    ca = pki.create_swarm_pki(d, "lab", [1, 2])
    return d, ca


def test_each_robot_gets_its_own_identity_and_never_the_ca_key(swarm_pki):
    d, ca = swarm_pki
    for i in (1, 2):
        tls = d / f"robot{i}" / "tls"
        assert sorted(p.name for p in tls.iterdir()) == ["ca.pem", "cert.pem", "key.pem"]
        assert pki.check_identity(tls, pki.robot_name(i)).common_name == f"robot-{i}"
        assert stat.S_IMODE((tls / "key.pem").stat().st_mode) == 0o600
    assert pki.check_identity(d / "monitor", pki.MONITOR_NAME)
    assert stat.S_IMODE((ca / "ca.key").stat().st_mode) == 0o600
    assert not list(d.glob("robot*/**/ca.key")) and not list(d.glob("monitor/**/ca.key"))
    issued = json.loads((ca / "issued.json").read_text())
    assert [e["common_name"] for e in issued] == ["robot-1", "robot-2", "monitor"]


def test_a_folder_that_is_not_the_robots_own_is_refused_with_the_reason(swarm_pki, tmp_path):
    d, _ = swarm_pki
    with pytest.raises(pki.PkiError, match="certificate of 'robot-1', not of 'robot-2'"):
        pki.check_identity(d / "robot1" / "tls", pki.robot_name(2))
    other = pki.create_ca(tmp_path / "other", "other")
    forged = pki.issue(other, pki.robot_name(2), tmp_path / "forged")
    (forged / "ca.pem").write_bytes((d / "robot2" / "tls" / "ca.pem").read_bytes())  # claims the swarm's CA
    with pytest.raises(pki.PkiError, match="not signed by the swarm CA"):
        pki.check_identity(forged, pki.robot_name(2))
    (forged / "key.pem").write_bytes((d / "robot2" / "tls" / "key.pem").read_bytes())
    with pytest.raises(pki.PkiError, match="is not the key of"):
        pki.check_identity(forged, pki.robot_name(2))
    with pytest.raises(pki.PkiError, match="no ca.pem"):
        pki.check_identity(tmp_path, pki.robot_name(2))
    with pytest.raises(pki.PkiError, match="not an identity"):
        pki.issue(d / "ca", "robot-two", tmp_path / "x")


def test_the_access_control_lets_robot_i_say_only_its_own_keys_and_zenoh_accepts_it(swarm_pki):
    d, _ = swarm_pki
    keys = Keys("lab")
    acl = access_control(keys, [1, 2, 3], revoked=["robot-3"])
    assert acl["default_permission"] == "deny"
    assert [s["cert_common_names"] for s in acl["subjects"]] == [["robot-1"], ["robot-2"], ["monitor"]]
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["speak-robot-2"]["key_exprs"] == ["dinerf/lab/theta/2/*/*", "dinerf/lab/status/2"]
    assert rules["serve-robot-2"]["key_exprs"] == ["dinerf/lab/latest/2", "dinerf/lab/keyframes/2"]
    assert rules["token-robot-2"]["key_exprs"] == ["dinerf/lab/alive/2"]
    ingress = [r for r in acl["rules"] if r["flows"] == ["ingress"]]
    assert all(set(r["messages"]) <= {"declare_subscriber", "query", "declare_liveliness_subscriber",
                                       "liveliness_query"} for r in ingress if r["id"] == "listen")
    monitor = next(p for p in acl["policies"] if p["subjects"] == ["monitor"])
    assert monitor["rules"] == ["listen", "send"]  # it may watch, never speak
    assert not any("robot-3" in r["id"] for r in acl["rules"])  # revoked: no subject, everything denied
    tls = d / "robot1" / "tls"
    cfg = TransportConfig(listen=["tls/127.0.0.1:7447"], tls_root_ca=str(tls / "ca.pem"), tls_cert=str(tls / "cert.pem"),
                          tls_key=str(tls / "key.pem"), access_control=acl)
    assert cfg.mtls()  # on by default whenever TLS is used
    conf = cfg.to_zenoh()  # Zenoh parses the section (a wrong message kind or field is refused here)
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True


def _doc(d, secure: bool, **security):
    sec = security_sections(insecure=not secure)
    return swarm_doc("lab", [1, 2], "shared", "full", network={**sec["network"],
                     "endpoints": loopback_endpoints([1, 2], 7500, tls=secure)}, security={**sec["security"], **security})


def test_plain_tcp_needs_insecure_said_explicitly(swarm_pki, tmp_path):
    doc = _doc(tmp_path, secure=False)
    doc.pop("security")
    with pytest.raises(ConfigError, match="plain TCP, but the swarm is secure by default"):
        write_swarm_file(tmp_path / "swarm.toml", doc)
    cfg, _ = load_swarm_file(write_swarm_file(tmp_path / "swarm.toml", _doc(tmp_path, secure=False)))
    assert cfg.security.insecure and cfg.transport_for(1, [], []).listen == ["tcp/127.0.0.1:7501"]


def test_a_secure_swarm_hands_each_robot_its_certificate_and_the_access_control(swarm_pki):
    d, _ = swarm_pki
    cfg, base = load_swarm_file(write_swarm_file(d / "swarm.toml", _doc(d, secure=True)))
    t = cfg.transport_for(2, [], [], tls_dir=d / "robot2" / "tls")
    assert t.tls_cert == str(d / "robot2" / "tls" / "cert.pem") and t.mtls() and t.access_control["subjects"]
    assert t.listen == ["tls/127.0.0.1:7502"] and t.connect == ["tls/127.0.0.1:7501"]
    with pytest.raises(ConfigError, match="certificate of 'robot-1', not of 'robot-2'"):
        cfg.transport_for(2, [], [], tls_dir=d / "robot1" / "tls")
    with pytest.raises(ConfigError, match="is not tls/"):
        cfg.transport_for(2, ["tcp/127.0.0.1:9000"], [], tls_dir=d / "robot2" / "tls")
    mon = cfg.monitor_transport(base, ["tls/127.0.0.1:7501"])
    assert mon.tls_cert == str(d / "monitor" / "cert.pem") and mon.listen == []
    revoked, _ = load_swarm_file(write_swarm_file(d / "swarm.toml", _doc(d, secure=True, revoked=["robot-2"])))
    with pytest.raises(ConfigError, match="robot 2 is revoked"):
        revoked.transport_for(2, [], [], tls_dir=d / "robot2" / "tls")
    with pytest.raises(ConfigError, match="not an identity"):
        write_swarm_file(d / "swarm.toml", _doc(d, secure=True, revoked=["3"]))
