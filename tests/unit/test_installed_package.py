"""The package as a user installs it (not this checkout): the scenarios ship inside it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    p = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                        "--target", str(target), str(REPO)], capture_output=True, text=True,
                       env=dict(os.environ, TMPDIR=str(build)), cwd=build)
    if p.returncode != 0 and "setuptools" in (p.stderr + p.stdout):
        pytest.skip(f"cannot build the package here: {p.stderr.strip().splitlines()[-1]}")
    assert p.returncode == 0, p.stderr
    return target


def _agent(installed: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(installed), COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=120)


def test_scenarios_are_found_from_an_installed_package(installed, tmp_path):
    listed = _agent(installed, "scenario", "list", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "quickstart" in listed.stdout and "fault-link-cut" in listed.stdout
    shown = _agent(installed, "config", "show", "--scenario", "quickstart", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert str(installed / "scenarios" / "quickstart") in shown.stdout, "read from the installed copy"
    assert str(REPO) not in shown.stdout
