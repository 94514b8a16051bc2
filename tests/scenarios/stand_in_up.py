"""A stand-in for ``dinerf-agent up`` that trains nothing: it exercises the scenario *runner*.

It takes ``up``'s flags (and writes ``round`` = rounds completed, as the daemon does), listens on its ``--listen`` endpoints, and each "round" (a short sleep)
tries a TCP connection to every ``--connect`` endpoint, logging who answered as ``heard``. It
writes telemetry.jsonl, a checkpoint (the last round) that a restart resumes from, and
done.json. Used only by tests of the orchestration (timeline, kill/restart, cut links,
cleanup); the end-to-end tests run the real daemon.
"""

from __future__ import annotations

import argparse
import json
import socket
import threading
import time
import tomllib
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("up")
    ap.add_argument("--id", type=int, required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--swarm", required=True)
    ap.add_argument("--run-dir", required=True)
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--round-s", type=float, default=0.3)
    a = ap.parse_args()
    swarm = tomllib.loads(Path(a.swarm).read_text())
    rounds = swarm["training"]["rounds"]
    run = Path(a.run_dir)
    run.mkdir(parents=True, exist_ok=True)
    assert Path(a.data).is_dir(), a.data
    eps = {a.id: a.listen}
    if not a.listen:  # local mode: endpoints from the swarm file
        eps = {int(k): [v] for k, v in swarm["network"]["endpoints"].items()}
        a.listen = eps[a.id]
        a.connect = [v[0] for k, v in eps.items() if k != a.id]  # the runner passes neighbours only in netns
    servers = []
    for ep in a.listen:
        host, port = ep.split("/", 1)[1].rsplit(":", 1)
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, int(port)))
        s.listen(16)
        servers.append(s)
        threading.Thread(target=lambda s=s: [s.accept()[0].close() for _ in iter(int, 1)], daemon=True).start()
    ckpt = run / "checkpoint.json"
    start = json.loads(ckpt.read_text())["round"] if ckpt.is_file() else 0
    for k in range(start, rounds):
        time.sleep(a.round_s)
        heard = []
        for ep in a.connect:
            host, port = ep.split("/", 1)[1].rsplit(":", 1)
            try:
                socket.create_connection((host, int(port)), timeout=1.0).close()  # generous: a loaded CI machine
                heard.append(ep)
            except OSError:
                pass
        rec = {"robot": a.id, "round": k + 1, "time": time.time(), "loss": 1.0 / (k + 1), "psnr": None, "heard": heard,
               "bytes_in": {}, "bytes_out": 0, "steps": 1, "seconds_compute": a.round_s, "seconds_wait": 0.0}
        with (run / "telemetry.jsonl").open("a") as f:
            f.write(json.dumps(rec) + "\n")
        ckpt.write_text(json.dumps({"round": k + 1}))  # like the daemon: rounds completed
        print(f"round {k} heard {heard}", flush=True)
    (run / "done.json").write_text(json.dumps({"rounds": rounds}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
