"""Layering: pure protocol modules import neither zenoh nor torch; the two sessions (transport: the
swarm; ros_camera: the robot's own ROS 2 topics) never import torch."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _modules_after(imports: str) -> dict:
    code = (f"import sys, json; import {imports}; "
            "print(json.dumps({m: m in sys.modules for m in ('zenoh', 'torch')}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_pure_modules_import_neither_zenoh_nor_torch():
    loaded = _modules_after("protocol, protocol.keys, protocol.messages, protocol.codec, protocol.rounds, "
                            "protocol.membership, protocol.pki, protocol.acl, protocol.rmw_format")
    assert loaded == {"zenoh": False, "torch": False}


def test_transport_imports_zenoh_but_not_torch():
    for module in ("protocol.transport", "protocol.ros_camera"):
        assert _modules_after(module) == {"zenoh": True, "torch": False}, module


def test_only_transport_mentions_zenoh_and_nothing_mentions_torch():
    for path in (ROOT / "protocol").glob("*.py"):
        text = path.read_text()
        assert "import torch" not in text and "from torch" not in text, path
        if path.name not in ("transport.py", "ros_camera.py"):
            assert "import zenoh" not in text and "from zenoh" not in text, path
