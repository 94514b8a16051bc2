"""Roles for the identity tests: ``python -m tests.protocol.acl_peers ROLE [options]``.

- ``guard``: robot 1 of a secure swarm of robots 1-3 (its own certificate, mutual TLS, the
  swarm's access control); listens, and reports every put, reply and liveliness token that
  reaches it from another process (key and the label the sender wrote into it).
- ``speaker``: connects to the guard with whatever certificate it is given (none, another CA's,
  self-signed, a valid one) and says, under the label ``--label``, everything on the keys of the
  robots ``--claim``: theta and status puts, a liveliness token, answers on ``latest``. Reports
  whether a Zenoh session with the guard was ever established.

Each prints one JSON object per line and exits after ``--timeout`` seconds.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

from protocol.acl import access_control
from protocol.transport import TransportConfig, ZenohTransport
from tests.protocol import helpers

_lock = threading.Lock()
ROBOTS = [1, 2, 3]


def emit(event: str, **fields) -> None:
    with _lock:
        print(json.dumps({"event": event, **fields}), flush=True)


def _tls(folder: str, with_cert: bool = True) -> dict:
    d = Path(folder)
    tls = dict(tls_root_ca=str(d / "ca.pem"), tls_verify_name_on_connect=False)
    if with_cert:
        tls.update(tls_cert=str(d / "cert.pem"), tls_key=str(d / "key.pem"), enable_mtls=True)
    else:  # a TLS client that presents no certificate
        tls.update(enable_mtls=False)
    return tls


def role_guard(args) -> None:
    keys = helpers.keys()
    cfg = TransportConfig(listen=[f"tls/127.0.0.1:{args.port}"], lease_ms=1000, **_tls(args.tls),
                          access_control=access_control(keys, ROBOTS, revoked=args.revoked))
    with ZenohTransport(cfg, keys, 1) as net:
        net.declare_alive()
        net.set_latest(b"guard", round=0)
        net.subscribe(f"{keys.prefix}/**", lambda key, data: emit("put", key=key, label=data.decode(errors="replace")))
        net.watch_alive(lambda ids: emit("alive", ids=sorted(ids)))
        emit("ready")
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            for key, data in net.query_all(keys.latest_all(), timeout=0.5):
                if data != b"guard":
                    emit("reply", key=key, label=data.decode(errors="replace"))
            time.sleep(0.3)


def role_speaker(args) -> None:
    keys = helpers.keys()
    tls = _tls(args.tls, with_cert=not args.no_cert)
    cfg = TransportConfig(connect=[f"tls/127.0.0.1:{args.port}"], listen=[], lease_ms=1000,
                          reconnect_init_ms=100, reconnect_max_ms=300, **tls)
    label = args.label.encode()
    with ZenohTransport(cfg, keys, 99) as net:
        session = net.session
        tokens, queryables = [], []
        for j in args.claim:
            tokens.append(session.liveliness().declare_token(keys.alive(j)))
            key = keys.latest(j)
            queryables.append(session.declare_queryable(key, lambda q, key=key: q.reply(key, label)))
        emit("ready")
        linked = False
        deadline = time.monotonic() + args.timeout
        k = 1
        while time.monotonic() < deadline:
            linked = linked or bool(list(session.info.peers_zid()))
            for j in args.claim:
                net.publish(keys.theta(j, k, to=1), label, block=False)
                net.publish(keys.status(j), label, block=False)
            k += 1
            time.sleep(0.2)
        emit("done", linked=linked, rounds=k - 1)


ROLES = {"guard": role_guard, "speaker": role_speaker}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("role", choices=sorted(ROLES))
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--tls", required=True, help="a certificate folder (ca.pem, cert.pem, key.pem)")
    p.add_argument("--no-cert", action="store_true", help="present no client certificate")
    p.add_argument("--claim", type=int, action="append", default=[])
    p.add_argument("--label", default="")
    p.add_argument("--revoked", action="append", default=[])
    p.add_argument("--timeout", type=float, default=10.0)
    args = p.parse_args()
    ROLES[args.role](args)


if __name__ == "__main__":
    main()
