"""The centralised baseline: one model trained on every robot's views with the true poses.

It is the paper's point of comparison, and the same :class:`RobotTrainer` as a swarm robot
(pose fixed, no neighbours), so the comparison measures the distribution, not two codebases.
Held-out views follow the split's rule (indices 0, k, 2k, ...), so the baseline and a split of
the same dataset are scored on the same views.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable

import torch

from agent.data.split import estimate_scene_box
from agent.data.views import DataError, Views
from agent.geometry import box_from_center
from agent.trainer import RobotTrainer, TrainConfig


def holdout_indices(count: int, every: int) -> list[int]:
    """The held-out views of a dataset: 0, k, 2k, ... (none when every == 0)."""
    return list(range(0, count, every)) if every > 0 else []


@dataclass
class BaselineRun:
    trainer: RobotTrainer
    train_indices: list[int]
    test_indices: list[int]
    step_seconds: list[float]  # wall time of every step (grid updates included)
    box_source: str


def train_baseline(
    views: Views,
    cfg: TrainConfig,
    holdout_every: int = 8,
    on_step: Callable[[int], None] | None = None,
) -> BaselineRun:
    """Train on all views but the held-out ones, in the dataset's own (world) frame."""
    test = holdout_indices(len(views), holdout_every)
    train = [i for i in range(len(views)) if i not in set(test)]
    if not train:
        raise DataError(f"no training views left: {len(views)} views, every {holdout_every}th held out")
    center, half, source = estimate_scene_box(views)
    cfg = replace(cfg, pose=replace(cfg.pose, mode="fixed"))
    trainer = RobotTrainer(views.subset(train), cfg, box_from_center(center, half))
    times: list[float] = []
    last = time.perf_counter()

    def step_done(i: int) -> None:
        nonlocal last
        now = time.perf_counter()
        times.append(now - last)
        last = now
        if on_step is not None:
            on_step(i)

    trainer.train(cfg.total_steps, step_done)
    return BaselineRun(trainer, train, test, times, source)


@torch.no_grad()
def evaluate_heldout(run: BaselineRun, views: Views, with_ssim: bool = True) -> dict[str, list[float]]:
    """PSNR/SSIM (white background) on the held-out views, in the world frame."""
    return run.trainer.evaluate(views.subset(run.test_indices), frame="local", with_ssim=with_ssim)
