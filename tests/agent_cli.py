"""`dinerf-agent` as a user runs it, in a fresh interpreter on this checkout (for tests of the commands)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRY = "import sys; sys.argv[0] = 'dinerf-agent'; from cli.main import main; main()"


def agent(*args: str, cwd: Path = ROOT, timeout: float = 300, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``dinerf-agent ARGS``; ``env``: variables added to this process's environment."""
    full = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    return subprocess.run([sys.executable, "-c", ENTRY, *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout, env=full)
