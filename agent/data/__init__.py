"""Datasets: loaders for every supported layout, the procedural scene, and splitting into robots.

The names below are imported lazily, so that ``import agent.data.views`` (which the CLI's error
handler does) does not pull in OpenCV or pycolmap.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Views": "agent.data.views",
    "DataError": "agent.data.views",
    "load_views": "agent.data.loaders",
    "load_transforms": "agent.data.transforms_json",
    "load_colmap": "agent.data.colmap",
    "load_llff": "agent.data.llff",
    "resize_views": "agent.data.images",
    "ProceduralConfig": "agent.data.procedural",
    "procedural_views": "agent.data.procedural",
    "render_procedural": "agent.data.procedural",
    "SplitConfig": "agent.data.split",
    "SplitResult": "agent.data.split",
    "RobotSplit": "agent.data.split",
    "split_views": "agent.data.split",
    "split_dataset": "agent.data.split",
    "write_split": "agent.data.split",
    "estimate_scene_box": "agent.data.capture",
    "capture_warnings": "agent.data.capture",
    "write_views_folder": "agent.data.folder",
    "read_scene": "agent.data.folder",
    "read_truth": "agent.data.folder",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'agent.data' has no attribute {name!r}")
