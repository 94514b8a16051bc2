"""Shared pieces of the namespace tests: the skip reason, TCP probes run inside a namespace."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from cli.scenario.netns import netns_unavailable_reason

_REASON = netns_unavailable_reason()
needs_netns = pytest.mark.skipif(_REASON is not None, reason=f"netns tests skipped: {_REASON}")

SERVER = """
import socket, sys
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.bind(('0.0.0.0', int(sys.argv[1]))); s.listen(64)
print('listening', flush=True)
while True:
    c, _ = s.accept()
    try:
        while True:  # messages: 8-byte length, payload; answered by b'ok' once all of it arrived
            head = b''
            while len(head) < 8:
                d = c.recv(8 - len(head))
                if not d: raise OSError
                head += d
            left = int.from_bytes(head, 'big')
            while left:
                d = c.recv(min(left, 1 << 20))
                if not d: raise OSError
                left -= len(d)
            c.sendall(b'ok')
    except OSError:
        pass
    c.close()
"""

CLIENT = """
import socket, sys, time, json
host, port, n, size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
t = time.monotonic()
try:
    s = socket.create_connection((host, port), timeout=float(sys.argv[5]))
    connect = time.monotonic() - t
    rtts = []
    for _ in range(n):
        t1 = time.monotonic(); s.sendall(size.to_bytes(8, 'big') + b'x' * size); got = b''
        while len(got) < 2:
            d = s.recv(2)
            if not d: raise OSError('closed')
            got += d
        rtts.append(time.monotonic() - t1)
    print(json.dumps({'ok': True, 'connect': connect, 'rtts': rtts}))
except OSError as e:
    print(json.dumps({'ok': False, 'error': str(e), 'after': time.monotonic() - t}))
"""


def start_echo(lab, robot: int, port: int = 9000) -> subprocess.Popen:
    p = subprocess.Popen(lab.exec_argv(robot, [sys.executable, "-c", SERVER, str(port)]), stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "listening"
    return p


def probe(lab, src: int, addr: str, port: int = 9000, n: int = 3, size: int = 100, timeout: float = 2.0) -> dict:
    import json

    p = subprocess.run(lab.exec_argv(src, [sys.executable, "-c", CLIENT, addr, str(port), str(n), str(size), str(timeout)]),
                       capture_output=True, text=True, timeout=120)
    return json.loads(p.stdout.strip().splitlines()[-1])


def wait_gone(names: list[str], timeout: float = 10.0) -> list[str]:
    from cli.scenario.netns import list_namespaces

    deadline = time.monotonic() + timeout
    while True:
        left = [n for n in names if n in list_namespaces()]
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.1)
