"""Transport and codec figures on loopback: put latency/throughput between two processes, and
bytes on the wire for float32/float16 with and without zstd.

    .venv/bin/python benchmarks/bench_transport.py [--sizes 1 4 16 64] [--repeats 3]

The receiver runs in a child process (its own Zenoh session); latency is measured from just
before ``publish`` in this process to the subscriber callback in the child, on the shared
monotonic clock. Payloads are random bytes (the transport does not compress).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from protocol import codec  # noqa: E402
from protocol.keys import Keys  # noqa: E402
from protocol.messages import ModelSpec, ThetaSnapshot  # noqa: E402

SWARM = "bench"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def receiver(port: int) -> None:
    from protocol.transport import TransportConfig, ZenohTransport

    keys = Keys(SWARM)
    cfg = TransportConfig(listen=[f"tcp/127.0.0.1:{port}"])
    lock = threading.Lock()

    def on_data(key: str, data: bytes) -> None:
        t = time.monotonic()
        with lock:
            print(json.dumps({"key": key, "bytes": len(data), "t": t}), flush=True)

    with ZenohTransport(cfg, keys, 1) as net:
        net.subscribe(keys.theta_of(0), on_data)
        net.declare_alive()
        print(json.dumps({"ready": True}), flush=True)
        sys.stdin.read()
    os._exit(0)


def bench_puts(sizes_mb: list[int], repeats: int) -> None:
    from protocol.transport import TransportConfig, ZenohTransport

    port = free_port()
    child = subprocess.Popen([sys.executable, __file__, "--role", "receiver", "--port", str(port)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert json.loads(child.stdout.readline()).get("ready")
        keys = Keys(SWARM)
        cfg = TransportConfig(listen=[], connect=[f"tcp/127.0.0.1:{port}"])
        with ZenohTransport(cfg, keys, 0) as net:
            present = threading.Event()
            net.watch_alive(lambda ids: present.set() if 1 in ids else None)
            if not present.wait(20):
                raise SystemExit("receiver never appeared")
            rng = np.random.default_rng(0)
            print("\nput between two processes on loopback (CongestionControl.BLOCK, reliable)")
            print(f"{'size':>6} {'put() s':>9} {'latency s':>10} {'MB/s':>8}   (median of {repeats})")
            round_no = 0
            for size in sizes_mb:
                payload = rng.bytes(size * 1024 * 1024)
                put_s, latency = [], []
                for _ in range(repeats):
                    t0 = time.monotonic()
                    net.publish(keys.theta(0, round_no, to=1), payload)
                    t1 = time.monotonic()
                    line = json.loads(child.stdout.readline())
                    assert line["bytes"] == len(payload)
                    put_s.append(t1 - t0)
                    latency.append(line["t"] - t0)
                    round_no += 1
                lat = statistics.median(latency)
                print(f"{size:>4}MB {statistics.median(put_s):>9.3f} {lat:>10.3f} {size / lat:>8.0f}")
    finally:
        child.stdin.close()
        child.wait(timeout=10)


def bench_wire_sizes(num_values: int) -> None:
    rng = np.random.default_rng(1)
    datasets = {
        "trained-like N(0, 0.1)": rng.normal(0, 0.1, num_values).astype(np.float32),
        "hash-grid init U(+-1e-4)": rng.uniform(-1e-4, 1e-4, num_values).astype(np.float32),
    }
    print(f"\nbytes on the wire for {num_values * 4 / 2**20:.0f} MB of float32 parameters")
    print(f"{'data':<26} {'encoding':<10} {'bytes':>11} {'ratio':>6} {'encode s':>9} {'decode s':>9} "
          f"{'max rel err':>12}")
    for label, values in datasets.items():
        tensors = {"params": values}
        spec = ModelSpec.from_tensors(tensors)
        expect = codec.Expectation(SWARM, spec)
        msg = ThetaSnapshot(SWARM, 0, 0, 0, spec.signature(), tensors)
        for dtype in ("float32", "float16"):
            for compression in ("none", "zstd"):
                t0 = time.perf_counter()
                data = codec.encode(msg, wire_dtype=dtype, compression=compression, level=3)
                t1 = time.perf_counter()
                got = codec.decode(data, expect).tensors["params"]
                t2 = time.perf_counter()
                rel = float(np.max(np.abs(got - values)) / np.max(np.abs(values)))
                name = {"float32": "f32", "float16": "f16"}[dtype] + "+" + compression
                print(f"{label:<26} {name:<10} {len(data):>11} {len(data) / (num_values * 4):>6.3f} "
                      f"{t1 - t0:>9.3f} {t2 - t1:>9.3f} {rel:>12.2e}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 4, 16, 64], help="payload sizes in MB")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--wire-mb", type=int, default=16, help="snapshot size for the wire-size table")
    parser.add_argument("--role", default="bench", choices=["bench", "receiver"], help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role == "receiver":
        receiver(args.port)
        return
    bench_puts(args.sizes, args.repeats)
    bench_wire_sizes(args.wire_mb * 1024 * 1024 // 4)


if __name__ == "__main__":
    main()
