"""A hostile peer for the system tests: floods a real swarm's keys with malformed messages.

Run as ``python tests/system/rogue.py SWARM_TOML DURATION_S``. It joins the swarm's Zenoh network
(connecting to every robot's endpoint), learns the swarm's real model layout, and every 0.3 s
publishes, on each robot's theta and status keys, one message of every malformed kind below,
forged as if that robot had sent it. Prints one JSON line per burst.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from protocol import codec  # noqa: E402
from protocol.messages import Alignment, ModelSpec, Status, ThetaSnapshot  # noqa: E402
from tests.protocol.helpers import reframe, rle_zstd_frame  # noqa: E402

# reason the daemon must count -> how to forge it (spec, swarm, robot j, round k) -> (key, bytes)
EXPECTED_REASONS = (
    "wrong_swarm", "bad_signature", "bad_shape", "bad_length", "bad_checksum", "non_finite",
    "bad_magic", "garbage", "decompression_bomb", "too_large", "sender_mismatch", "stale_round",
    "too_far_ahead", "bad_kind", "bad_field",
)


def forge(spec: ModelSpec, swarm: str, keys, j: int, other: int, k: int, tensors: dict, to: int
          ) -> list[tuple[str, str, bytes]]:
    """Messages forged as robot j's, on the keys robot ``to`` listens to."""
    sig = spec.signature()

    def snap(**kw) -> ThetaSnapshot:
        args = dict(swarm=swarm, sender=j, round=k, epoch=0, signature=sig, tensors=tensors)
        args.update(kw)
        return ThetaSnapshot(**args)

    good = codec.encode(snap())
    nan = {n: a.copy() for n, a in tensors.items()}
    first = next(iter(nan))
    nan[first].reshape(-1)[7] = np.nan
    raw_nan = b"".join(np.ascontiguousarray(a, dtype="<f4").tobytes() for a in nan.values())
    wrong_shapes = {n: np.zeros((a.size + 2,), np.float32) for n, a in tensors.items()}
    flipped = bytearray(good)
    flipped[-9] ^= 0x10
    other_spec = ModelSpec(spec.params, {**dict(spec.arch), "forged": True})
    status_ok = Status(swarm, j, k, 0, 0, "x", 1.0, None, [0.0] * 7, [], 0, 0, {}, Alignment.IDENTITY, "x", 0.0, 0.0, 0.0)
    t = keys.theta(j, k, to=to)
    return [
        ("wrong_swarm", t, codec.encode(snap(swarm="not-this-swarm"))),
        ("bad_signature", t, codec.encode(snap(signature=other_spec.signature()))),
        ("bad_shape", t, codec.encode(snap(tensors=wrong_shapes))),
        ("bad_length", t, good[:-11]),
        ("bad_checksum", t, bytes(flipped)),
        ("non_finite", t, reframe(good, raw=raw_nan)),
        ("bad_magic", t, np.random.default_rng(k).bytes(512)),
        ("garbage", t, b"DNRF" + (4).to_bytes(4, "little") + b"\xc1\xc1\xc1\xc1"),
        ("decompression_bomb", t, reframe(good, payload=rle_zstd_frame(2**31, True))),
        ("too_large", t, reframe(good, raw_length=2**40)),
        ("sender_mismatch", t, codec.encode(snap(sender=other))),
        ("stale_round", keys.theta(j, 0, to=to), codec.encode(snap(round=0))) if k >= 2 else None,
        ("too_far_ahead", keys.theta(j, k + 60, to=to), codec.encode(snap(round=k + 60))),
        ("bad_kind", t, codec.encode(status_ok)),
        ("bad_field", keys.status(j), reframe(codec.encode(status_ok), raw=b"\x93\x01\x02\x03")),
    ]


def main(swarm_toml: str, duration: float) -> None:
    from agent.daemon import model_spec
    from agent.data.folder import read_scene
    from agent.data.loaders import load_views
    from agent.swarm import build_robot
    from cli.swarm_file import load_swarm_file
    from protocol.keys import Keys
    from protocol.transport import TransportConfig, ZenohTransport

    cfg, base = load_swarm_file(Path(swarm_toml))
    ids = cfg.swarm.robots
    scene = read_scene(base / cfg.swarm.scene)
    setup = build_robot(ids[0], load_views(base / f"robot{ids[0]}"), scene.box_from_shared, cfg.training)
    spec = model_spec(setup)
    tensors = {n: t.numpy().astype(np.float32) for n, t in setup.trainer.theta().items()}
    keys = Keys(cfg.swarm.name)
    endpoints = [cfg.endpoint(i) for i in ids if cfg.endpoint(i)]
    net = ZenohTransport(TransportConfig(listen=[], connect=endpoints), keys, robot_id=max(ids) + 100).open()
    rounds_seen = {i: 0 for i in ids}

    def on_status(key: str, data: bytes) -> None:  # learn the swarm's round to forge near it
        try:
            msg = codec.decode(data, codec.Expectation(cfg.swarm.name), kind="status")
            rounds_seen[msg.sender] = max(rounds_seen[msg.sender], msg.round)
        except Exception:
            pass

    net.subscribe(keys.status_all(), on_status)
    t_end = time.monotonic() + duration
    bursts = 0
    while time.monotonic() < t_end:
        for j in ids:
            other = next(i for i in ids if i != j)
            k = rounds_seen[j] + 1
            for victim in ids:
                if victim == j:
                    continue
                for item in forge(spec, cfg.swarm.name, keys, j, other, k, tensors, to=victim):
                    if item is not None:
                        net.publish(item[1], item[2])
        bursts += 1
        print(json.dumps({"burst": bursts, "rounds": rounds_seen}), flush=True)
        time.sleep(0.3)
    net.close()


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
