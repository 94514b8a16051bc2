"""Mutual TLS + access control against plain TCP: the same real swarm (`dinerf-agent up` robots on
loopback, tests/system/harness.py), run alternately insecure and secure, in one benchmark run.

    nice .venv/bin/python benchmarks/bench_tls.py [--robots 3] [--rounds 8] [--repeats 2] [--log2-hashmap 14] \
        [--puts 4 16 64]

Per mode, over every robot's rounds after the first (the first includes start-up): the round
time (between consecutive telemetry lines), the time waiting at the barrier, the duration of the
snapshot puts, and the snapshot bytes received per link per round. Runs alternate (tcp, tls,
tls, tcp, tcp, tls ...) so that a change of machine load, or going first, hits both modes alike.

``--puts``: also the raw transport, without training: puts of random payloads of these sizes
(MB) to a subscriber in another process, over plain TCP and over mutual TLS with access control,
alternately; latency from just before ``publish`` to the subscriber's callback (one monotonic
clock), median of ``--repeats`` x 3.

Zenoh's shared memory is off in both modes (``--shm`` leaves it on): between processes of one
host it carries large payloads past the link, TCP or TLS, and robots on separate machines share
no memory.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.system.harness import make_swarm  # noqa: E402


NO_SHM = {"transport/shared_memory/enabled": "false"}


def run_once(tmp: Path, secure: bool, robots: int, rounds: int, log2_hashmap: int, shm: bool) -> dict[str, list[float]]:
    training = {"rounds": rounds, "train": {"field": {"grid": {"log2_hashmap_size": log2_hashmap}}}}
    swarm = make_swarm(tmp, robots=robots, topology="full", training=training, secure=secure,
                       network={} if shm else {"extra": NO_SHM})
    t0 = time.monotonic()
    try:
        swarm.start_all()
        swarm.wait_all(timeout=600)
    finally:
        swarm.stop()
    wall = time.monotonic() - t0
    out: dict[str, list[float]] = {"round_s": [], "wait_s": [], "put_s": [], "bytes_per_link": [], "wall_s": [wall]}
    for i in swarm.robots:
        tel = swarm.telemetry(i)
        assert [t.round for t in tel] == list(range(1, rounds + 1)), f"robot {i} did not train every round"
        for prev, t in zip(tel, tel[1:]):
            out["round_s"].append(t.monotonic - prev.monotonic)
            out["wait_s"].append(t.seconds_wait)
            out["put_s"].extend(t.seconds_last_put.values())
            out["bytes_per_link"].extend(float(b) for b in t.bytes_in.values())
        if secure:
            assert "secure: mutual TLS" in swarm.log_text(i)
        else:
            assert "INSECURE" in swarm.log_text(i)
    return out


def _transport(pki_dir: str | None, robot: int, listen: list[str], connect: list[str], shm: bool):
    from protocol.acl import access_control
    from protocol.keys import Keys
    from protocol.transport import TransportConfig, ZenohTransport

    keys = Keys("bench")
    extra = {} if shm else dict(NO_SHM)
    if pki_dir is None:
        return ZenohTransport(TransportConfig(listen=listen, connect=connect, extra=extra), keys, robot)
    d = Path(pki_dir) / f"robot{robot}" / "tls"
    cfg = TransportConfig(listen=[e.replace("tcp/", "tls/") for e in listen], connect=[e.replace("tcp/", "tls/") for e in connect],
                          tls_root_ca=str(d / "ca.pem"), tls_cert=str(d / "cert.pem"), tls_key=str(d / "key.pem"),
                          tls_verify_name_on_connect=False, access_control=access_control(keys, [0, 1]), extra=extra)
    return ZenohTransport(cfg, keys, robot)


def receiver(port: int, pki_dir: str | None, shm: bool) -> None:
    """Robot 1: print the arrival time of every snapshot of robot 0."""
    with _transport(pki_dir, 1, [f"tcp/127.0.0.1:{port}"], [], shm) as net:
        net.subscribe(net.keys.theta_of(0), lambda key, data: print(json.dumps({"bytes": len(data), "t": time.monotonic()}),
                                                                    flush=True))
        net.declare_alive()
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.read()
    os._exit(0)


def bench_puts(sizes_mb: list[int], repeats: int, pki_dir: str, mode: str, shm: bool) -> dict[int, list[float]]:
    import socket

    import numpy as np

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    tls = (["--pki", pki_dir] if mode == "tls" else []) + (["--shm"] if shm else [])
    child = subprocess.Popen([sys.executable, __file__, "--role", "receiver", "--port", str(port), *tls],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    out: dict[int, list[float]] = {}
    try:
        assert json.loads(child.stdout.readline()).get("ready")
        with _transport(pki_dir if mode == "tls" else None, 0, [], [f"tcp/127.0.0.1:{port}"], shm) as net:
            present = threading.Event()
            net.watch_alive(lambda ids: present.set() if 1 in ids else None)
            if not present.wait(20):
                raise SystemExit(f"{mode}: the receiver never appeared")
            rng, k = np.random.default_rng(0), 0
            for size in sizes_mb:
                payload = rng.bytes(size * 1024 * 1024)
                for _ in range(repeats):
                    t0 = time.monotonic()
                    net.publish(net.keys.theta(0, k, to=1), payload)
                    line = json.loads(child.stdout.readline())
                    assert line["bytes"] == len(payload)
                    out.setdefault(size, []).append(line["t"] - t0)
                    k += 1
    finally:
        child.stdin.close()
        child.wait(timeout=10)
    return out


def report_puts(sizes_mb: list[int], repeats: int, shm: bool) -> None:
    from protocol.pki import create_swarm_pki

    latency: dict[str, dict[int, list[float]]] = {"tcp": {}, "tls": {}}
    with tempfile.TemporaryDirectory() as d:
        create_swarm_pki(Path(d), "bench", [0, 1])
        for _ in range(3):
            for mode in ("tcp", "tls"):
                for size, v in bench_puts(sizes_mb, repeats, d, mode, shm).items():
                    latency[mode].setdefault(size, []).extend(v)
    print(f"\nput to another process on loopback, latency to the subscriber's callback (median); shared memory "
          f"{'on' if shm else 'off'}")
    print(f"{'size':>6} {'tcp s':>8} {'tls s':>8} {'tcp MB/s':>9} {'tls MB/s':>9} {'tls/tcp':>8}")
    for size in sizes_mb:
        a, b = (statistics.median(latency[m][size]) for m in ("tcp", "tls"))
        print(f"{size:>4}MB {a:8.3f} {b:8.3f} {size / a:9.0f} {size / b:9.0f} {b / a:8.3f}")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--robots", type=int, default=3)
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--log2-hashmap", type=int, default=14, help="hash table size of the model (bytes per snapshot)")
    p.add_argument("--puts", type=int, nargs="*", default=[], help="also raw puts of these sizes (MB)")
    p.add_argument("--shm", action="store_true", help="leave Zenoh's shared memory on (one host only)")
    p.add_argument("--role", default="bench", choices=["bench", "receiver"], help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--pki", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.role == "receiver":
        receiver(args.port, args.pki, args.shm)
        return
    if args.puts:
        report_puts(args.puts, args.repeats, args.shm)
    if args.rounds <= 0:
        return
    figures: dict[str, dict[str, list[float]]] = {"tcp": {}, "tls": {}}
    with tempfile.TemporaryDirectory() as d:
        for r in range(args.repeats):
            for mode in (("tcp", "tls") if r % 2 == 0 else ("tls", "tcp")):  # each mode first as often
                got = run_once(Path(d) / f"{mode}{r}", mode == "tls", args.robots, args.rounds, args.log2_hashmap,
                               args.shm)
                for k, v in got.items():
                    figures[mode].setdefault(k, []).extend(v)
                print(f"run {r + 1}/{args.repeats} {mode}: wall {got['wall_s'][0]:.1f} s, median round "
                      f"{statistics.median(got['round_s']):.3f} s", flush=True)
    print(f"\n{args.robots} robots, full topology, {args.rounds} rounds x {args.repeats} runs per mode, "
          f"log2 hash table {args.log2_hashmap}, shared memory {'on' if args.shm else 'off'}")
    print(f"{'':6} {'round s (median)':>17} {'round s (mean)':>15} {'wait s':>8} {'put ms':>8} {'KB/link/round':>14}")
    for mode, f in figures.items():
        print(f"{mode:6} {statistics.median(f['round_s']):17.3f} {statistics.fmean(f['round_s']):15.3f} "
              f"{statistics.median(f['wait_s']):8.3f} {1000 * statistics.median(f['put_s']):8.2f} "
              f"{statistics.median(f['bytes_per_link']) / 1e3:14.1f}")
    tcp, tls = (statistics.median(figures[m]["round_s"]) for m in ("tcp", "tls"))
    print(f"TLS round time / TCP round time: {tls / tcp:.3f} (median)")


if __name__ == "__main__":
    main()
