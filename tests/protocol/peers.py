"""Roles for the multi-process Zenoh tests: ``python -m tests.protocol.peers ROLE [options]``.

Each role prints one JSON object per line on stdout ({"event": ..., ...}) so the test can follow
it, and exits by itself after ``--timeout`` seconds whatever happens, so a hung Zenoh session
can never outlive the test run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import threading
import time

import numpy as np

from protocol import codec
from protocol.keys import ForeignKey
from protocol.messages import Alignment, ModelSpec, Rejected, Status, ThetaSnapshot
from protocol.rounds import Mailbox
from protocol.transport import TransportConfig, ZenohTransport
from tests.protocol import helpers

_print_lock = threading.Lock()


def emit(event: str, **fields) -> None:
    with _print_lock:
        print(json.dumps({"event": event, "t": time.monotonic(), **fields}), flush=True)


def big_tensors(size_mb: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    values = size_mb * 1024 * 1024 // 4
    return {
        "grid.table": rng.standard_normal(values - 64 * 64, dtype=np.float32),
        "mlp.0.weight": rng.standard_normal((64, 64), dtype=np.float32),
    }


def digest(tensors: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name, t in tensors.items():
        h.update(name.encode())
        h.update(np.ascontiguousarray(t, dtype="<f4").tobytes())
    return h.hexdigest()


def transport(args, robot_id: int) -> ZenohTransport:
    tls = {}
    proto, host = "tcp", "127.0.0.1"
    if args.tls_dir:  # mutual TLS with <tls-dir>/<ca>.pem and <tls-dir>/<cert>.pem/.key
        proto, host = "tls", "localhost"
        d = args.tls_dir
        tls = dict(tls_root_ca=f"{d}/{args.tls_ca}.pem", tls_cert=f"{d}/{args.tls_cert}.pem",
                   tls_key=f"{d}/{args.tls_cert}.key", enable_mtls=True)
    listen = [f"{proto}/{host}:{args.listen}"] if args.listen else []
    connect = [f"{proto}/{host}:{p}" for p in args.connect]
    cfg = TransportConfig(listen=listen, connect=connect, multicast_scouting=False, lease_ms=2000, **tls)
    return ZenohTransport(cfg, helpers.keys(), robot_id).open()


def wait_for_alive(net: ZenohTransport, robot_id: int, timeout: float) -> bool:
    seen = threading.Event()
    net.watch_alive(lambda ids: seen.set() if robot_id in ids else None)
    return seen.wait(timeout)


def wait_for_stdin_close() -> None:
    sys.stdin.read()


# ----------------------------------------------------------------------------- roles


def role_big_publisher(args) -> None:
    """Robot 0: publish one large snapshot with BLOCK once robot 1 is alive."""
    tensors = big_tensors(args.size_mb, args.seed)
    spec = ModelSpec.from_tensors(tensors, {"test": "big"})
    with transport(args, 0) as net:
        net.declare_alive()
        emit("ready")
        if not wait_for_alive(net, 1, 20):
            emit("error", detail="receiver never appeared")
            return
        msg = ThetaSnapshot(helpers.SWARM, 0, 1, 0, spec.signature(), tensors)
        t0 = time.monotonic()
        data = codec.encode(msg, compression=args.compression, level=1)
        t1 = time.monotonic()
        net.publish(net.keys.theta(0, 1, to=1), data)
        t2 = time.monotonic()
        net.set_latest(data)
        emit("published", bytes=len(data), encode_s=t1 - t0, put_s=t2 - t1, t_put=t1)
        wait_for_stdin_close()  # stay up until the test is done, so the transfer can finish


def role_big_receiver(args) -> None:
    """Robot 1: receive robot 0's snapshot, decode it and check it bit for bit."""
    expected = big_tensors(args.size_mb, args.seed)
    spec = ModelSpec.from_tensors(expected, {"test": "big"})
    expect = codec.Expectation(helpers.SWARM, spec, frozenset({0}))
    want = digest(expected)
    del expected
    done = threading.Event()

    def on_theta(key: str, data: bytes) -> None:
        t_in = time.monotonic()
        try:
            msg = codec.decode(data, expect, kind="theta", key=net.keys.parse(key))
            ok = digest(msg.tensors) == want
            emit("received", bytes=len(data), ok=ok, round=msg.round, t_in=t_in,
                 decode_s=time.monotonic() - t_in)
        except Rejected as exc:
            emit("received", bytes=len(data), ok=False, reason=exc.reason, detail=exc.detail, t_in=t_in)
        done.set()

    with transport(args, 1) as net:
        net.subscribe(net.keys.theta_of(0), on_theta)
        net.declare_alive()
        emit("ready")
        done.wait(args.timeout)
        t0 = time.monotonic()
        data = net.query(net.keys.latest(0), timeout=20)  # the same snapshot through the queryable
        t1 = time.monotonic()
        try:
            msg = codec.decode(data, expect, kind="theta") if data is not None else None
            emit("queried", bytes=len(data or b""), ok=msg is not None and digest(msg.tensors) == want,
                 seconds=t1 - t0)
        except Rejected as exc:
            emit("queried", bytes=len(data), ok=False, reason=exc.reason)
        emit("stats", **net.stats())


def role_alive(args) -> None:
    """Hold a liveliness token until killed (or stdin closes)."""
    with transport(args, args.id) as net:
        net.declare_alive()
        emit("ready")
        wait_for_stdin_close()


def role_watcher(args) -> None:
    """Report the live set on every change, with the monotonic time it was seen."""
    with transport(args, args.id) as net:
        net.declare_alive()
        net.watch_alive(lambda ids: emit("alive", ids=sorted(ids)))
        emit("ready")
        wait_for_stdin_close()


def role_runtime_threads(args) -> None:
    """Once linked to robot 1, report the names of Zenoh's runtime threads in this process."""
    with transport(args, args.id) as net:
        net.declare_alive()
        if not wait_for_alive(net, 1, 20):
            emit("error", detail="robot 1 never appeared")
            return
        names: list[str] = []
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:  # the runtime's workers (rx and tx) come up one by one
            names = []
            for t in os.listdir("/proc/self/task"):
                try:
                    names.append(open(f"/proc/self/task/{t}/comm").read().strip())
                except OSError:  # a thread that just ended
                    pass
            names = sorted(n for n in names if n[:3] in ("rx-", "tx-"))
            if (sum(n.startswith("rx-") for n in names) >= TransportConfig().rx_threads
                    and any(n.startswith("tx-") for n in names)):
                break
            time.sleep(0.1)
        emit("threads", names=names)


def role_latest_server(args) -> None:
    """Robot 0 runs rounds 0..3, publishing each snapshot and serving the newest on latest/0."""
    spec = helpers.small_spec()
    with transport(args, 0) as net:
        net.declare_alive()
        for r in range(4):
            msg = ThetaSnapshot(helpers.SWARM, 0, r, 0, spec.signature(), helpers.small_tensors(seed=r))
            data = codec.encode(msg)
            net.publish(net.keys.theta(0, r, to=0), data)
            net.set_latest(data)
        emit("ready", rounds=4)
        wait_for_stdin_close()


def role_sink(args) -> None:
    """Subscribe to robot 0's snapshots and drop them; hold a token (the test freezes this one)."""
    with transport(args, args.id) as net:
        net.subscribe(net.keys.theta_of(0), lambda key, data: None)
        net.declare_alive()
        emit("ready")
        wait_for_stdin_close()


def role_stuck_pusher(args) -> None:
    """Robot 0, linked to a sink (robot 1) and a healthy robot 2: on a "go" line on stdin, push
    ``--size-mb`` snapshots of 1 MB to robot 1 from a sender thread, as the daemon does; after 8 s
    report every live set seen meanwhile and every put that waited. The test freezes robot 1
    first, so the puts block on its link."""
    seen: list[list[int]] = []
    with transport(args, 0) as net:
        net.declare_alive()
        linked = threading.Event()

        def on_alive(ids: frozenset[int]) -> None:
            seen.append(sorted(ids))
            if ids >= {0, 1, 2}:
                linked.set()

        net.watch_alive(on_alive)
        if not linked.wait(20):
            emit("error", detail=f"robots 1 and 2 never appeared: {seen}")
            return
        emit("ready")
        sys.stdin.readline()
        del seen[:-1]  # the live set at "go", then every change
        payload = os.urandom(1 << 20)
        t_go = time.monotonic()
        blocked: list[tuple[float, float]] = []  # (start after go, seconds) of every put that waited

        def push() -> None:
            for r in range(args.size_mb):
                t0 = time.monotonic()
                net.publish(net.keys.theta(0, r, to=1), payload)
                if time.monotonic() - t0 > 0.1:
                    blocked.append((round(t0 - t_go, 2), round(time.monotonic() - t0, 2)))
                time.sleep(0.05)

        threading.Thread(target=push, daemon=True).start()
        time.sleep(8.0)
        emit("done", live_sets=list(seen), blocked=blocked)
        wait_for_stdin_close()


def role_late_joiner(args) -> None:
    """Start late, fetch robot 0's newest snapshot through the queryable."""
    expect = helpers.expectation()
    with transport(args, 2) as net:
        t0 = time.monotonic()
        data = None
        while data is None and time.monotonic() - t0 < 10:  # the link may need a moment
            data = net.query(net.keys.latest(0), timeout=2.0)
        if data is None:
            emit("fetched", ok=False)
            return
        msg = codec.decode(data, expect, kind="theta", key=net.keys.parse(net.keys.latest(0)))
        emit("fetched", ok=True, round=msg.round, sender=msg.sender, seconds=time.monotonic() - t0,
             digest=digest(msg.tensors), want=digest(helpers.small_tensors(seed=3)))


def rogue_messages() -> list[tuple[str, str, bytes]]:
    """(expected outcome, key, bytes) the rogue sends, in order; the last one is a valid snapshot."""
    keys = helpers.keys()
    out = [(reason, keys.theta(key_id, helpers.ROUND, to=0), data)
           for _, reason, data, key_id in helpers.malformed_cases()]
    status = codec.encode(Status(helpers.SWARM, 1, helpers.ROUND, 0, 0, "train", 1.0, None, [0.0] * 7, [], 0, 0, {},
                                 Alignment.IDENTITY, "", 0.0, 0.0, 0.0))
    out += [
        ("bad_kind", keys.theta(1, helpers.ROUND, to=0), status),
        ("foreign_key", f"dinerf/{helpers.SWARM}/theta/abc/{helpers.ROUND}/0", helpers.valid_frame()),
        ("stale_round", keys.theta(1, helpers.ROUND - 3, to=0), helpers.valid_frame(round=helpers.ROUND - 3)),
        ("too_far_ahead", keys.theta(1, helpers.ROUND + 50, to=0), helpers.valid_frame(round=helpers.ROUND + 50)),
        ("accepted", keys.theta(1, helpers.ROUND, to=0), helpers.valid_frame()),
    ]
    return out


def role_rogue(args) -> None:
    """Publish every malformed kind on the swarm's theta keys, once robot 0 listens."""
    with transport(args, 1) as net:
        if not wait_for_alive(net, 0, 20):
            emit("error", detail="receiver never appeared")
            return
        messages = rogue_messages()
        for _, key, data in messages:
            net.publish(key, data)
        emit("sent", count=len(messages))
        wait_for_stdin_close()


def role_rogue_receiver(args) -> None:
    """Robot 0 at round ROUND of ROUND + 10: decode everything on theta/*/*, count outcomes by reason."""
    expect = helpers.expectation()
    mailbox: Mailbox = Mailbox(max_ahead=2, current_round=helpers.ROUND, last_round=helpers.ROUND + 10)
    counts: dict[str, int] = {}
    total = len(rogue_messages())
    lock = threading.Lock()
    done = threading.Event()

    def count(outcome: str) -> None:
        with lock:
            counts[outcome] = counts.get(outcome, 0) + 1
            if sum(counts.values()) >= total:
                done.set()

    def on_theta(key: str, data: bytes) -> None:
        try:
            parsed = net.keys.parse(key)
        except ForeignKey:
            count("foreign_key")
            return
        try:
            msg = codec.decode(data, expect, kind="theta", key=parsed)
            mailbox.offer(msg.sender, msg.round, msg)
            count("accepted")
        except Rejected as exc:
            count(exc.reason)

    with transport(args, 0) as net:
        net.subscribe(net.keys.theta_all(), on_theta)
        net.declare_alive()
        emit("ready")
        done.wait(args.timeout - 2)
        accepted = mailbox.items(helpers.ROUND)
        emit("counts", counts=counts, expected_total=total,
             accepted_senders=sorted(accepted), accepted_ok=all(
                 np.array_equal(accepted[s].tensors[n], t) for s in accepted
                 for n, t in helpers.small_tensors().items()),
             callback_errors=net.stats()["callback_errors"])


def role_publish_many(args) -> None:
    """Sixteen threads put at once, each on keys of its own (one per round, as snapshots are), more
    keys than the transport keeps publishers for; a slow subscriber keeps each put in flight."""
    from protocol.transport import TransportError

    net = transport(args, 0)
    received: list[str] = []
    lock = threading.Lock()

    def slow(key: str, data: bytes) -> None:
        time.sleep(0.005)
        with lock:
            received.append(key)

    net.subscribe(net.keys.theta_all(), slow)
    failures: list[str] = []
    threads, rounds = 16, 25

    def sender(t: int) -> None:
        for r in range(1, rounds + 1):
            try:
                net.publish(net.keys.theta(t + 1, r, to=0), b"x" * 1000)
            except TransportError as e:
                failures.append(str(e))

    workers = [threading.Thread(target=sender, args=(t,)) for t in range(threads)]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    deadline = time.monotonic() + 10
    while len(set(received)) < threads * rounds and time.monotonic() < deadline:
        time.sleep(0.1)
    emit("published", sent=threads * rounds, received=len(set(received)), failures=failures[:3],
         failed=len(failures), publishers_kept=len(net._publishers))
    net.close()


def role_self_check(args) -> None:
    """One session alone: callback errors are contained and counted, close() is idempotent."""
    from protocol.transport import TransportError

    net = transport(args, 0)
    got = threading.Event()

    def explode(key: str, data: bytes) -> None:
        raise RuntimeError("a bug in a user callback")

    net.subscribe(net.keys.theta_of(0), explode)
    sub = net.subscribe(net.keys.theta_of(0), lambda key, data: got.set())
    net.publish(net.keys.theta(0, 1, to=0), b"x" * 10)
    delivered = got.wait(5)
    time.sleep(0.2)
    errors = net.stats()["callback_errors"]
    sub.undeclare()
    sub.undeclare()  # twice is fine
    net.set_latest(b"newest", round=5)
    served = net.query(net.keys.latest(0), timeout=2)
    served_since = [net.query(net.keys.latest_since(0, k), timeout=2) for k in (5, 6)]
    bad_parameter = net.query(net.keys.latest(0) + "?min_round=x", timeout=2)
    net.set_latest(b"newest" * 4, round=5, deltas=((3, b"d4"), (4, b"d5")))  # the pushes since round 3
    from_held = [[d.decode() for _, d in net.query_all(net.keys.latest_since(0, 5, held=h), timeout=2)]
                 for h in (3, 4, 2)]
    missing = net.query(net.keys.latest(7), timeout=2)
    net.close()
    net.close()
    try:
        net.publish(net.keys.theta(0, 2, to=0), b"y")
        after_close = "no error"
    except TransportError as exc:
        after_close = str(exc)
    emit("checked", delivered=delivered, callback_errors=errors, served=served.decode() if served else None,
         served_since=[x.decode() if x else None for x in served_since],
         bad_parameter=bad_parameter.decode() if bad_parameter else None, from_held=from_held, missing=missing, after_close=after_close, stats=net.stats())


ROLES = {
    "runtime-threads": role_runtime_threads,
    "sink": role_sink,
    "stuck-pusher": role_stuck_pusher,
    "self-check": role_self_check,
    "big-publisher": role_big_publisher,
    "big-receiver": role_big_receiver,
    "alive": role_alive,
    "publish-many": role_publish_many,
    "watcher": role_watcher,
    "latest-server": role_latest_server,
    "late-joiner": role_late_joiner,
    "rogue": role_rogue,
    "rogue-receiver": role_rogue_receiver,
}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=sorted(ROLES))
    parser.add_argument("--listen", type=int, default=0)
    parser.add_argument("--connect", type=int, action="append", default=[])
    parser.add_argument("--id", type=int, default=0)
    parser.add_argument("--size-mb", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compression", default="zstd")
    parser.add_argument("--timeout", type=float, default=30.0)
    parser.add_argument("--tls-dir", default="")
    parser.add_argument("--tls-ca", default="ca")
    parser.add_argument("--tls-cert", default="robot")
    args = parser.parse_args()
    watchdog = threading.Timer(args.timeout, lambda: os._exit(3))  # never outlive the test
    watchdog.daemon = True
    watchdog.start()
    ROLES[args.role](args)
    sys.stdout.flush()
    os._exit(0)  # do not wait on Zenoh's background threads at interpreter exit


if __name__ == "__main__":
    main()
