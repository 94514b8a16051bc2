"""Baselines already trained are not trained again: the same models, data, settings and code.

A scenario's baselines (the centralised model, each robot alone) cost more than its swarm: three
models of as many steps as a robot, on the same two cores. They depend only on the dataset, the
split, the training settings, the steps and the code, so a report keeps them under a key of all
of these (``~/.cache/dinerf/baselines/<key>/``, or ``$DINERF_CACHE``) and the next report of the
same inputs (a rebuilt report, a fault scenario beside its fault-free one, a re-run) reads them
back. Any change to a file of ``agent/`` makes a new key: a cached figure is never one of older code.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from agent.evaluation.baselines import AloneScores, Baselines, BaselineFailure, CentralisedScores

__all__ = ["baseline_key", "load_cached", "store_cached", "cache_root", "dataset_fingerprint"]


def cache_root() -> Path:
    base = os.environ.get("DINERF_CACHE") or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "dinerf"
    return Path(base) / "baselines"


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """sha256 over every source file of ``agent/`` (the trainer, the data, the evaluation)."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def dataset_fingerprint(dataset: str) -> object:
    """A procedural spec as it is; a folder or file by its files' names and sizes."""
    path = Path(dataset)
    if not path.exists():
        return dataset
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return [[str(p.relative_to(path.parent)), p.stat().st_size] for p in files]


def baseline_key(inputs: dict) -> str:
    text = json.dumps({"inputs": inputs, "code": code_digest()}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def load_cached(key: str) -> Baselines | None:
    folder = cache_root() / key
    try:
        doc = json.loads((folder / "baselines.json").read_text())
        renders = np.load(folder / "renders.npy") if (folder / "renders.npy").is_file() else None
        central = CentralisedScores(**doc["centralised"], renders=renders)
        alone = None if "alone" not in doc else {int(i): AloneScores(**a) for i, a in doc["alone"].items()}
        return Baselines(int(doc["steps"]), central, alone)
    except (OSError, ValueError, KeyError, TypeError):
        return None  # absent or unreadable: trained again


def store_cached(key: str, baselines: Baselines) -> None:
    """Keep ``baselines`` under ``key``; one whose robot alone failed is not kept (it would hide the failure)."""
    if baselines.alone and any(isinstance(a, BaselineFailure) for a in baselines.alone.values()):
        return
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=root))
    try:
        (tmp / "baselines.json").write_text(json.dumps(baselines.to_dict(), indent=2))
        if baselines.centralised.renders is not None:
            np.save(tmp / "renders.npy", baselines.centralised.renders)
        target = root / key
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
