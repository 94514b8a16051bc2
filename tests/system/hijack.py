"""A rogue that tries to steer a real swarm's rounds with well-formed messages (system tests).

Run as ``python tests/system/hijack.py SWARM_TOML DURATION_S LISTEN [CERT_DIR]``. It listens on
LISTEN for the robots to connect to it as to a peer, prints ``ready``, learns the model layout,
and at once:

- answers on every robot's ``latest`` queryable with a snapshot of that robot claiming round
  1,000,000, and another claiming the swarm's last round (a robot that joins at the first reply
  would train nothing and finish at once);
- re-publishes every real snapshot it sees to the same receiver as copies from the far future
  (round + 3 and + 6): a barrier that trusts them stops waiting, a robot skips its training;
- re-publishes every real snapshot under its own round with other values, ``REPLAY_DELAY_S``
  later (a replay that replaces the copy already taken in would change the model).

Without CERT_DIR the swarm under test is insecure (plain TCP) and the rogue speaks for every
robot: this attacks the round logic. With CERT_DIR (a robot's ``tls/`` folder: a stolen but valid
certificate, LISTEN a ``tls/`` endpoint) it speaks only for the *other* robots, which the
swarm's access control must refuse. Prints one JSON line per second with what it sent (and
whether any peer is linked to it).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from protocol import codec  # noqa: E402
from protocol.compression import BaseBook  # noqa: E402
from protocol.messages import ThetaSnapshot  # noqa: E402

FUTURE = (3, 6)  # rounds ahead of a real snapshot its copies claim
# The replay goes out this long after the real snapshot was seen, so that it meets a copy already
# taken in. In an insecure swarm a forgery that overtakes the real copy is the real copy as far as
# anyone can tell; that is what TLS and the access control are for (tests/system/test_secure_swarm.py).
REPLAY_DELAY_S = 0.1


def _transport_config(listen: str, cert_dir: str | None):
    from protocol.transport import TransportConfig

    if cert_dir is None:
        return TransportConfig(listen=[listen]), None
    from protocol.pki import describe, robot_id_of

    d = Path(cert_dir)
    own = robot_id_of(describe(d / "cert.pem").common_name)
    return TransportConfig(listen=[listen], tls_root_ca=str(d / "ca.pem"), tls_cert=str(d / "cert.pem"),
                           tls_key=str(d / "key.pem"), tls_verify_name_on_connect=False), own


def main(swarm_toml: str, duration: float, listen: str, cert_dir: str | None = None) -> None:
    from agent.daemon import model_spec
    from agent.data.folder import read_scene
    from agent.data.loaders import load_views
    from agent.swarm import build_robot
    from cli.swarm_file import load_swarm_file
    from protocol.keys import Keys
    from protocol.transport import ZenohTransport

    cfg, base = load_swarm_file(Path(swarm_toml))
    ids = cfg.swarm.robots
    scene = read_scene(base / cfg.swarm.scene)
    setup = build_robot(ids[0], load_views(base / f"robot{ids[0]}"), scene.box_from_shared, cfg.training)
    spec = model_spec(setup)
    zeros = {n: np.zeros(t.shape, np.float32) for n, t in setup.trainer.theta().items()}
    keys = Keys(cfg.swarm.name)
    expect = codec.Expectation(cfg.swarm.name, spec=spec)
    tcfg, own = _transport_config(listen, cert_dir)
    targets = [j for j in ids if j != own]  # with a robot's certificate: speak as the others
    net = ZenohTransport(tcfg, keys, robot_id=max(ids) + 100).open()
    sent = {"latest_answers": 0, "future_copies": 0, "replays": 0, "linked": False}
    lock = threading.Lock()

    def snapshot(j: int, k: int, tensors: dict) -> bytes:
        return codec.encode(ThetaSnapshot(cfg.swarm.name, j, k, 0, spec.signature(), tensors), spec=spec)

    def answer(j: int):
        forged = [snapshot(j, 1_000_000, zeros), snapshot(j, cfg.training.rounds, zeros)]

        def on_query(query) -> None:  # two forged answers to every query on robot j's latest
            with query:
                for data in forged:
                    query.reply(keys.latest(j), data)
            with lock:
                sent["latest_answers"] += len(forged)
        return on_query

    queryables = [net.session.declare_queryable(keys.latest(j), answer(j)) for j in targets]

    seen: set[tuple[int, int, int]] = set()  # (sender, round, to): our own copies come back to us too

    def on_theta(key: str, data: bytes) -> None:  # runs on a Zenoh thread: hand over, never publish here
        try:
            parsed = keys.parse(key)
            msg = codec.decode(data, expect, kind="theta", key=parsed)
        except Exception:
            return
        if msg.sender not in targets:
            return
        with lock:
            first = (msg.sender, msg.round, parsed.receiver) not in seen
            seen.update((msg.sender, msg.round + d, parsed.receiver) for d in (0, *FUTURE))
        if first:
            threading.Thread(target=copy, args=(msg, parsed.receiver), daemon=True).start()

    # The swarm's pushes are deltas (delta+uniform, the default): the rogue follows each sender's
    # model from theta^0 as a receiver does, and forges plain float32 frames of it
    book = BaseBook()
    for j in targets:
        book.seed(j, {n: t.numpy() for n, t in setup.trainer.theta().items()})

    def tensors_of(msg: ThetaSnapshot) -> dict:
        got = book.resolve(msg, spec)
        return zeros if isinstance(got, str) else got.tensors

    def copy(msg: ThetaSnapshot, to: int) -> None:
        j, k = msg.sender, msg.round
        try:
            tensors = tensors_of(msg)
            other = {n: a + 0.5 for n, a in tensors.items()}
            time.sleep(REPLAY_DELAY_S)
            net.publish(keys.theta(j, k, to=to), snapshot(j, k, other))
            with lock:
                sent["replays"] += 1
            for ahead in FUTURE:
                if k + ahead <= cfg.training.rounds:
                    net.publish(keys.theta(j, k + ahead, to=to), snapshot(j, k + ahead, tensors))
                    with lock:
                        sent["future_copies"] += 1
        except Exception as e:
            print(json.dumps({"error": f"{type(e).__name__}: {e}"}), flush=True)

    net.subscribe(keys.theta_all(), on_theta)
    print("ready", flush=True)
    t_end = time.monotonic() + duration
    while time.monotonic() < t_end:
        with lock:
            sent["linked"] = sent["linked"] or bool(list(net.session.info.peers_zid()))
            print(json.dumps(sent), flush=True)
        time.sleep(1.0)
    for q in queryables:
        q.undeclare()
    net.close()


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3], sys.argv[4] if len(sys.argv) > 4 else None)
