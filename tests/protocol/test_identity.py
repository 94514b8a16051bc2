"""Identity and authorisation over real Zenoh sessions in separate processes (tests/protocol/acl_peers.py).

A guard (robot 1 of a secure swarm of robots 1-3) listens; speakers connect with no certificate,
one from another CA, a self-signed one, robot 2's valid one and the monitor's, and each says
everything on the keys of robot 3 (and robot 2's own, for robot 2 and the outsiders). Only
robot 2's own keys may reach the guard, and only robot 2 and the monitor may even get a link.
"""

from __future__ import annotations

import datetime as dt
import time
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from protocol import pki
from tests.protocol.helpers import free_port

MODULE = "tests.protocol.acl_peers"


def _self_signed(folder: Path, cn: str) -> Path:
    """A certificate naming ``cn``, signed by its own key (and trusting only itself)."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])
    now = dt.datetime.now(dt.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost")]), critical=False)
            .sign(key, hashes.SHA256()))
    folder.mkdir(parents=True)
    pem = cert.public_bytes(serialization.Encoding.PEM)
    (folder / "cert.pem").write_bytes(pem)
    (folder / "ca.pem").write_bytes(pem)
    (folder / "key.pem").write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                       serialization.NoEncryption()))
    return folder


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("pki")
    ca = pki.create_swarm_pki(d, "testswarm", [1, 2, 3])
    other = pki.create_ca(d / "other-ca", "other")
    return {
        "guard": d / "robot1" / "tls",
        "robot2": d / "robot2" / "tls",
        "monitor": d / "monitor",
        "otherca": pki.issue(other, pki.robot_name(2), d / "other-robot2"),
        "selfsigned": _self_signed(d / "self-robot2", pki.robot_name(2)),
        "ca": ca,
    }


def _events(peer, timeout: float) -> list[dict]:
    """Every event of a peer, after it exits by itself."""
    peer.proc.wait(timeout=timeout)
    time.sleep(0.2)  # the reader thread drains the pipe
    out = []
    while not peer.events.empty():
        out.append(peer.events.get())
    return out


def _start(peers, certs, speakers: dict[str, tuple[str, ...]], revoked: tuple[str, ...] = ()):
    port = str(free_port())
    guard = peers("guard", "--port", port, "--tls", str(certs["guard"]), *[a for r in revoked for a in ("--revoked", r)],
                  timeout=7.0, module=MODULE)
    guard.expect("ready", 20)
    return guard, {label: peers("speaker", "--port", port, "--label", label, *args, timeout=4.5, module=MODULE)
                   for label, args in speakers.items()}


def _collect(guard, started) -> tuple[dict, list[dict]]:
    said = {label: [e for e in _events(p, 30) if e["event"] == "done"] for label, p in started.items()}
    heard = _events(guard, 30)
    for label, done in said.items():
        assert done, f"speaker {label} never finished: {started[label].stderr_tail()}"
    return {label: done[0] for label, done in said.items()}, heard


def test_outsiders_are_refused_at_the_link_and_a_robot_cannot_speak_as_another(peers, certs):
    """Also, beside it (at once, to save time): a guard that revokes robot 2 gives it a link
    (Zenoh's TLS checks no revocation list) but nothing robot 2 says arrives."""
    claim23 = ("--claim", "2", "--claim", "3")
    speakers = {
        "nocert": ("--tls", str(certs["robot2"]), "--no-cert", *claim23),  # trusts the swarm CA, shows nothing
        "otherca": ("--tls", str(certs["otherca"]), *claim23),
        "selfsigned": ("--tls", str(certs["selfsigned"]), *claim23),
        "robot2": ("--tls", str(certs["robot2"]), *claim23),  # valid: its own keys pass, robot 3's must not
        "monitor": ("--tls", str(certs["monitor"]), "--claim", "3"),
    }
    running = _start(peers, certs, speakers)
    revoking = _start(peers, certs, {"robot2": ("--tls", str(certs["robot2"]), "--claim", "2")},
                      revoked=(pki.robot_name(2),))
    said, heard = _collect(*running)
    links = {label: d["linked"] for label, d in said.items()}
    print(f"linked: {links}")
    assert links == {"nocert": False, "otherca": False, "selfsigned": False, "robot2": True, "monitor": True}
    puts = [(e["key"].split("/")[2:4], e["label"]) for e in heard if e["event"] == "put"]
    replies = [(e["key"].split("/")[2:4], e["label"]) for e in heard if e["event"] == "reply"]
    alive = set().union(*[set(e["ids"]) for e in heard if e["event"] == "alive"])
    print(f"the guard heard {len(puts)} puts, {len(replies)} replies, tokens of {sorted(alive)}")
    # the positive control: robot 2's own theta, status and latest did arrive (the link was up)
    assert (["theta", "2"], "robot2") in puts and (["status", "2"], "robot2") in puts
    assert (["latest", "2"], "robot2") in replies and 2 in alive
    # and nothing else at all: no outsider's message, no robot 3 key, nothing from the monitor
    assert {label for _, label in puts + replies} == {"robot2"}
    assert all(kind_id[1] == "2" for kind_id, _ in puts + replies), sorted(set(map(str, puts + replies)))
    assert alive <= {1, 2}

    said, heard = _collect(*revoking)
    assert said["robot2"]["linked"]
    assert [e for e in heard if e["event"] in ("put", "reply")] == []
    assert all(set(e["ids"]) <= {1} for e in heard if e["event"] == "alive")
