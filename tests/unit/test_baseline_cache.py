"""Baselines kept under a key of everything they depend on, and read back as they were."""

from __future__ import annotations

import numpy as np

from agent.evaluation import AloneScores, BaselineFailure, Baselines, CentralisedScores
from agent.evaluation.baseline_cache import baseline_key, load_cached, store_cached


def test_baselines_come_back_as_stored_and_a_different_input_misses(tmp_path, monkeypatch):
    monkeypatch.setenv("DINERF_CACHE", str(tmp_path))
    renders = np.random.default_rng(0).integers(0, 256, (2, 4, 5, 3), dtype=np.uint8)
    stored = Baselines(300, CentralisedScores(psnr=25.5, ssim=0.9, seconds=12.0, views=2, renders=renders),
                       {1: AloneScores(20.0, 0.8, 18.0, 0.7, seconds=5.0)})
    key = baseline_key({"dataset": "procedural:views=8", "steps": 300})
    assert load_cached(key) is None
    store_cached(key, stored)
    got = load_cached(key)
    assert got.to_dict() == stored.to_dict() and np.array_equal(got.centralised.renders, renders)
    assert baseline_key({"dataset": "procedural:views=8", "steps": 301}) != key
    failed = Baselines(300, stored.centralised, {1: BaselineFailure("RuntimeError: x")})
    other = baseline_key({"dataset": "procedural:views=9"})
    store_cached(other, failed)
    assert load_cached(other) is None  # a failure is never served as if it had been trained
