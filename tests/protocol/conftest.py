"""Fixtures for the protocol tests: child processes running roles of tests/protocol/peers.py."""

from __future__ import annotations

import json
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


class Peer:
    """A child process running one role of tests/protocol/peers.py."""

    def __init__(self, role: str, *args: str, timeout: float = 40.0, module: str = "tests.protocol.peers"):
        self.role = role
        self.stderr = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", module, role, "--timeout", str(timeout), *args],
            cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.stderr, text=True,
        )
        self.events: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                self.events.put(json.loads(line))
            except json.JSONDecodeError:
                pass

    def expect(self, event: str, timeout: float, where=lambda e: True) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.role}: no {event!r} within {timeout} s; stderr:\n{self.stderr_tail()}")
            try:
                e = self.events.get(timeout=min(left, 0.5))
            except queue.Empty:
                if self.proc.poll() is not None and self.events.empty():
                    raise AssertionError(f"{self.role} exited ({self.proc.returncode}) before {event!r}; "
                                         f"stderr:\n{self.stderr_tail()}")
                continue
            if e.get("event") == "error":
                raise AssertionError(f"{self.role}: {e}")
            if e.get("event") == event and where(e):
                return e

    def stderr_tail(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-3000:]

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()  # roles waiting on stdin exit cleanly
                self.proc.wait(timeout=5)
            except Exception:
                pass
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=5)


@pytest.fixture
def peers():
    started: list[Peer] = []

    def start(role: str, *args: str, timeout: float = 40.0, module: str = "tests.protocol.peers") -> Peer:
        p = Peer(role, *args, timeout=timeout, module=module)
        started.append(p)
        return p

    yield start
    for p in started:
        p.stop()
