"""A hostile robot: the real ``dinerf-agent up``, speaking only as itself, with one change.

Run as ``python tests/system/hostile.py ATTACK up --id I --data ... [any option of up]``. It
starts the real CLI in this process after replacing one or two methods of the real daemon
(``agent.daemon.Daemon``); everything else (its training, barrier, heartbeats, certificates,
keys) is the real robot's. It models a robot that was captured, crashed into a bad state or runs
buggy code. ATTACK, or several joined by ``+``:

- ``future``: every heartbeat claims the swarm's last round, and its ``latest`` queryable answers
  with a valid snapshot of that round holding -10 times its model (a forged catch-up model);
- ``nan``: its snapshots hold NaN (a broken encoder); it keeps heartbeating;
- ``noise`` / ``huge`` / ``minus_ten`` / ``replay``: from round ``HOSTILE_FROM`` (1) on, it sends as
  its own model Gaussian noise of each tensor's RMS / 1e30 everywhere / -10 times its model / its
  model of that first round, every round;
- ``poison``: one of those per round, in that order, then ``replay`` to the end;
- ``silent`` (a baseline, not an attack): it trains but sends nothing, neither snapshots nor
  heartbeats, and holds its liveliness token (a robot whose link died with its token alive).

Its forged snapshots are plain float32 frames (a robot may send those whatever the swarm's
compression is; a 1e30 model has no deltas).
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

POISONS = ("noise", "huge", "minus_ten", "replay")
ATTACKS = ("future", "nan", *POISONS, "poison", "silent")
HOSTILE_FROM = int(os.environ.get("HOSTILE_FROM", "1"))  # the first round whose snapshot is forged


def forge(kind: str, round_index: int, theta: dict[str, np.ndarray], memory: dict) -> dict[str, np.ndarray]:
    """The model sent instead of ``theta`` (``memory`` keeps the replayed model and the noise source)."""
    if kind == "poison":
        kind = POISONS[min(round_index - HOSTILE_FROM, len(POISONS) - 1)]
    memory.setdefault("first", {n: a.copy() for n, a in theta.items()})
    rng = memory.setdefault("rng", np.random.default_rng(round_index))
    if kind == "huge":
        return {n: np.full_like(a, 1e30) for n, a in theta.items()}
    if kind == "minus_ten":
        return {n: -10 * a for n, a in theta.items()}
    if kind == "replay":
        return memory["first"]
    if kind == "noise":
        return {n: (rng.standard_normal(a.shape) * np.sqrt(np.mean(a * a))).astype(np.float32) for n, a in theta.items()}
    raise ValueError(kind)


def _frame(daemon, round_index: int, tensors: dict[str, np.ndarray]) -> bytes:
    from protocol import codec
    from protocol.messages import ThetaSnapshot

    msg = ThetaSnapshot(swarm=daemon.swarm.name, sender=daemon.robot_id, round=round_index,
                        epoch=daemon.membership.epoch, signature=daemon.spec.signature(), tensors=tensors)
    return codec.encode(msg, spec=daemon.spec)


def _nan_frame(daemon, round_index: int, theta: dict[str, np.ndarray]) -> bytes:
    """A frame whose header and checksum are right and whose values are NaN (codec.encode refuses NaN)."""
    from tests.protocol.helpers import reframe

    raw = b"".join(np.full(a.shape, np.nan, "<f4").tobytes() for a in theta.values())
    return reframe(_frame(daemon, round_index, theta), raw=raw)


def _push(daemon, round_index: int, frame: bytes) -> None:
    """What the real exchange does with a snapshot, without its encoder: a put to every neighbour
    on its own key, and the same frame served as ``latest``."""
    for j in sorted(daemon.exchange.neighbours):
        daemon.net.publish(daemon.keys.theta(daemon.robot_id, round_index, to=j), frame)
    daemon.net.set_latest(frame, round=round_index)


def install(attacks: list[str], robot=None) -> None:
    """Replace the daemon's methods for ``attacks``: of the class (this process runs one robot),
    or of one ``robot`` (a Daemon of an in-process swarm, tests/system/test_loopback.py)."""
    import types

    from agent import daemon as daemon_module

    Daemon = daemon_module.Daemon
    honest_publish, honest_status, honest_model_changed = Daemon._publish_theta, Daemon._status_message, \
        Daemon._model_changed
    memory: dict = {}
    poison = [a for a in attacks if a in (*POISONS, "poison")]

    def publish(self, round_index: int) -> None:
        theta = daemon_module._to_numpy(self.trainer.theta())
        if "silent" in attacks:
            return
        if "nan" in attacks:
            _push(self, round_index, _nan_frame(self, round_index, theta))
        elif poison and round_index >= HOSTILE_FROM:
            _push(self, round_index, _frame(self, round_index, forge(poison[0], round_index, theta, memory)))
        else:
            honest_publish(self, round_index)
        if "future" in attacks:  # a forged catch-up model of the last round, on our latest queryable
            last = self.training.rounds
            self.net.set_latest(_frame(self, last, {n: -10 * a for n, a in theta.items()}), round=last)

    def status(self):
        msg = honest_status(self)
        return dataclasses.replace(msg, round=self.training.rounds) if "future" in attacks else msg

    def serve_forgery(self) -> None:  # from the start, before any snapshot: a joiner finds it at once
        honest_model_changed(self)
        if "future" in attacks and self.exchange.expect is not None:
            theta = daemon_module._to_numpy(self.trainer.theta())
            self.net.set_latest(_frame(self, self.training.rounds, {n: -10 * a for n, a in theta.items()}),
                                round=self.training.rounds)

    if robot is not None:
        robot._publish_theta = types.MethodType(publish, robot)
        robot.presence._status = types.MethodType(status, robot)  # the heartbeat holds the bound method
        serve_forgery(robot)
        return
    Daemon._publish_theta = publish
    Daemon._status_message = status
    Daemon._model_changed = serve_forgery
    if "silent" in attacks:
        from protocol.presence import Presence

        Presence._heartbeat = lambda self: None  # the heartbeat thread ends at once


def main(argv: list[str]) -> None:
    attacks = argv[0].split("+")
    unknown = [a for a in attacks if a not in ATTACKS]
    if unknown or not argv[1:] or argv[1] != "up":
        raise SystemExit(f"usage: hostile.py ATTACK[+ATTACK] up [options]; attacks: {', '.join(ATTACKS)}")
    install(attacks)
    from cli.main import main as cli_main

    sys.argv = ["dinerf-agent", *argv[1:]]
    cli_main()


if __name__ == "__main__":
    main(sys.argv[1:])
