"""Mutual TLS between robots: same CA connects, a certificate from another CA cannot."""

from __future__ import annotations

import shutil
import subprocess
import time

import pytest

from tests.protocol.helpers import free_port

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def _run(*args: str, cwd) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=30)


def _make_ca(d, name: str) -> None:
    _run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "2",
         "-subj", f"/CN=dinerf test {name}", "-keyout", f"{name}.key", "-out", f"{name}.pem",
         "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)


def _make_cert(d, name: str, ca: str) -> None:
    _run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-subj", "/CN=localhost",
         "-keyout", f"{name}.key", "-out", f"{name}.csr", cwd=d)
    (d / f"{name}.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                                    "extendedKeyUsage=serverAuth,clientAuth\nbasicConstraints=CA:FALSE\n")
    _run("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key", "-CAcreateserial",
         "-days", "2", "-out", f"{name}.pem", "-extfile", f"{name}.ext", cwd=d)


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    d = tmp_path_factory.mktemp("pki")
    _make_ca(d, "ca")
    _make_ca(d, "other-ca")
    _make_cert(d, "robot", "ca")
    _make_cert(d, "rogue", "other-ca")
    return d


def test_mtls_same_ca_connects_other_ca_is_refused(peers, pki):
    port = str(free_port())
    tls = ["--tls-dir", str(pki)]
    watcher = peers("watcher", "--listen", port, "--id", "0", *tls)
    watcher.expect("alive", 20, lambda e: e["ids"] == [0])
    # a rogue with a certificate from another CA (and trusting that CA) cannot join
    rogue = peers("alive", "--connect", port, "--id", "6", *tls, "--tls-ca", "other-ca", "--tls-cert", "rogue")
    rogue.expect("ready", 20)
    friend = peers("alive", "--connect", port, "--id", "1", *tls)
    friend.expect("ready", 20)
    joined = watcher.expect("alive", 10, lambda e: 1 in e["ids"])
    time.sleep(1.5)  # leave the rogue time to retry its connection
    rogue.stop()
    seen = [joined["ids"]]
    while not watcher.events.empty():
        seen.append(watcher.events.get().get("ids"))
    assert all(6 not in (ids or []) for ids in seen), seen
