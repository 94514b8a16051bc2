"""A userspace link emulator: delay, jitter, loss and a rate cap on an L2 link, for kernels without ``netem``.

Some kernels (this project's VMs among them) are built without ``sch_netem``, so ``tc qdisc ...
netem`` fails with "Specified qdisc kind is unknown". Then an impaired link a-b is built as
``a <-veth-> relay namespace <-veth-> b`` and this process, inside the relay namespace, copies
every Ethernet frame between its two interfaces through raw ``AF_PACKET`` sockets, holding each
frame for ``delay +- jitter`` and dropping it with probability ``loss``, independently in each
direction (as ``netem`` on both ends of the link would). With ``rate_mbit`` a frame also waits
for the wire: it leaves ``size / rate`` after the frame before it did, and a frame that finds
:data:`QUEUE_LIMIT` frames waiting is dropped (netem's default limit), so a robot's wireless
link of a few Mbit/s is slow the way a real one is. Frames keep their order (``netem`` may
reorder with jitter; TCP does not mind either way).

Details that make it correct rather than approximately right:

- ``PACKET_VNET_HDR`` carries the checksum-offload metadata across, so frames with a partial
  checksum (veth offloads) arrive with a correct one;
- the namespace builder sets ``gso_max_segs 1`` on the relayed veths, so a frame is one MTU-size
  packet and ``loss`` applies per packet, not per 64 KB GSO burst;
- frames the socket itself sent (``PACKET_OUTGOING``) are not forwarded again.

Control: one JSON object per line on stdin, e.g. ``{"delay_ms": 100, "jitter_ms": 10, "loss":
0.1, "rate_mbit": 20}``; ``{}`` makes the link clean. Prints ``ready`` once both sockets are bound, and a JSON
line of counters on every change and at exit (stdin closed, SIGTERM or SIGINT).

Run as ``python -m cli.scenario.linkemu IF_A IF_B`` (root, inside the relay namespace).
"""

from __future__ import annotations

import heapq
import json
import os
import random
import signal
import socket
import sys
import threading
import time

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
MAX_FRAME = 65536 + 64
QUEUE_LIMIT = 1000  # frames waiting in one direction before a rate-capped link drops (netem's default)


class Impairment:
    """The current delay/jitter/loss, shared by both directions (thread-safe by replacement)."""

    def __init__(self) -> None:
        self.delay = 0.0
        self.jitter = 0.0
        self.loss = 0.0
        self.rate = 0.0  # bits per second; 0: no cap

    def set(self, delay_ms: float = 0.0, jitter_ms: float = 0.0, loss: float = 0.0, rate_mbit: float = 0.0) -> None:
        if delay_ms < 0 or jitter_ms < 0 or not 0 <= loss < 1 or rate_mbit < 0:
            raise ValueError("need delay_ms >= 0, jitter_ms >= 0, 0 <= loss < 1, rate_mbit >= 0")
        self.delay, self.jitter, self.loss = delay_ms / 1000.0, jitter_ms / 1000.0, float(loss)
        self.rate = float(rate_mbit) * 1e6


class Direction:
    """Frames from ``src`` to ``dst``: a receiver thread queues them, a sender releases them on time."""

    def __init__(self, name: str, src: socket.socket, dst: socket.socket, imp: Impairment, rng: random.Random):
        self.name, self.src, self.dst, self.imp, self.rng = name, src, dst, imp, rng
        self.queue: list[tuple[float, int, bytes]] = []
        self.cv = threading.Condition()
        self.last_release = 0.0
        self.wire_free = 0.0  # when the frames accepted so far have all left the wire (rate cap)
        self.seq = 0
        self.counts = {"frames": 0, "bytes": 0, "dropped": 0, "sent": 0}

    def receive_forever(self) -> None:
        while True:
            data, addr = self.src.recvfrom(MAX_FRAME)
            if addr[2] == socket.PACKET_OUTGOING:
                continue
            self.counts["frames"] += 1
            self.counts["bytes"] += len(data)
            imp = self.imp
            if imp.loss and self.rng.random() < imp.loss:
                self.counts["dropped"] += 1
                continue
            now = time.monotonic()
            release = self.schedule(now, len(data), len(self.queue))
            if release is None:
                self.counts["dropped"] += 1
                continue
            with self.cv:  # the sender sends under the lock too, so a direct send never overtakes
                if release <= now and not self.queue:
                    self._send(data)
                    continue
                self.seq += 1
                heapq.heappush(self.queue, (release, self.seq, data))
                self.cv.notify()

    def schedule(self, now: float, size: int, waiting: int) -> float | None:
        """When a frame of ``size`` bytes arriving at ``now`` leaves, or None if the queue is full.

        Without a cap: after its delay. With one: after the wire has carried the frames before
        it and this one (``size * 8 / rate``), then its delay. Never before the frame before it.
        """
        imp = self.imp
        delay = max(imp.delay + (self.rng.uniform(-imp.jitter, imp.jitter) if imp.jitter else 0.0), 0.0)
        leaves = now
        if imp.rate:
            if waiting >= QUEUE_LIMIT:
                return None
            self.wire_free = leaves = max(now, self.wire_free) + size * 8 / imp.rate
        release = max(leaves + delay, self.last_release)  # keep the order
        self.last_release = release
        return release

    def send_forever(self) -> None:
        while True:
            with self.cv:
                while not self.queue:
                    self.cv.wait()
                release, _, data = self.queue[0]
                wait = release - time.monotonic()
                if wait > 0:
                    self.cv.wait(wait)
                    continue
                heapq.heappop(self.queue)
                self._send(data)

    def _send(self, data: bytes) -> None:
        try:
            self.dst.send(data)
            self.counts["sent"] += 1
        except OSError:  # the far interface is down (a cut): the frame is lost, as on a wire
            self.counts["dropped"] += 1


def open_interface(name: str) -> socket.socket:
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    s.bind((name, 0))
    return s


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print("usage: python -m cli.scenario.linkemu IF_A IF_B", file=sys.stderr)
        return 2
    a, b = (open_interface(n) for n in argv)
    imp = Impairment()
    rng = random.Random()
    dirs = [Direction(f"{argv[0]}->{argv[1]}", a, b, imp, rng), Direction(f"{argv[1]}->{argv[0]}", b, a, imp, rng)]
    for d in dirs:
        threading.Thread(target=d.receive_forever, daemon=True).start()
        threading.Thread(target=d.send_forever, daemon=True).start()

    exited = threading.Event()

    def report(event: str) -> None:
        if event == "exit":
            if exited.is_set():
                return
            exited.set()
        line = json.dumps({"event": event, "delay_ms": imp.delay * 1000, "jitter_ms": imp.jitter * 1000,
                           "loss": imp.loss, "rate_mbit": imp.rate / 1e6, **{d.name: dict(d.counts) for d in dirs}})
        sys.stdout.write(line + "\n")  # one write: a signal arriving mid-print cannot split the line
        sys.stdout.flush()

    def stop(signum, frame):  # noqa: ARG001
        report("exit")
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    print("ready", flush=True)
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            imp.set(**json.loads(line))
        except (ValueError, TypeError) as e:
            print(json.dumps({"event": "error", "error": str(e)}), flush=True)
            continue
        report("set")
    report("exit")
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the exit line is out: a late SIGTERM must not cut it
    return 0


if __name__ == "__main__":
    sys.exit(main())
