"""A robot's run folder: what the daemon keeps on disk, under which names, and how it comes back.

::

    <run dir>/checkpoint.pt       the robot's whole state after its last completed round (atomic)
    <run dir>/rounds/<k>.pt       field + grid + pose after round k (``daemon.keep_rounds``), for reports
    <run dir>/telemetry.jsonl     one agent.telemetry.RoundRecord per completed round
    <run dir>/events.jsonl        joins, alignment, failovers, silent neighbours ...
    <run dir>/done.json           written once every round is done
    <run dir>/sfm/                an images-only robot's own SfM, computed once, reused on restart
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from agent.data.views import Views
from agent.swarm import SwarmTrainingConfig, build_robot
from agent.trainer import RobotTrainer

__all__ = ["RunFolder", "RobotCheckpoint", "CHECKPOINT", "SFM_CACHE", "load_for_eval"]

CHECKPOINT = "checkpoint.pt"
SFM_CACHE = "sfm"
ROUNDS = "rounds"
TELEMETRY = "telemetry.jsonl"
EVENTS = "events.jsonl"
DONE = "done.json"


@dataclass
class RobotCheckpoint:
    """Everything a robot needs to resume, and to be rebuilt for evaluation."""

    round: int
    robot_id: int
    trainer: dict  # RobotTrainer.state_dict()
    elected: bool  # it was the reference (pose frozen)
    training: SwarmTrainingConfig  # load_for_eval rebuilds the robot from it
    box_from_shared: Tensor  # [4, 4]
    signature: str  # the model spec's: a checkpoint of another model is refused


def _atomic_torch_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


class RunFolder:
    """The files of one robot's run (see the module docstring)."""

    def __init__(self, path: str | Path, create: bool = True) -> None:
        self.path = Path(path)
        if create:
            self.path.mkdir(parents=True, exist_ok=True)

    checkpoint = property(lambda self: self.path / CHECKPOINT)
    telemetry = property(lambda self: self.path / TELEMETRY)
    events = property(lambda self: self.path / EVENTS)
    done = property(lambda self: self.path / DONE)
    sfm_cache = property(lambda self: self.path / SFM_CACHE)

    def round_path(self, round_index: int) -> Path:
        return self.path / ROUNDS / f"{round_index:05d}.pt"

    def snapshot_rounds(self) -> list[int]:
        """The rounds kept under ``rounds/`` (``daemon.keep_rounds``), in order."""
        return sorted(int(p.stem) for p in (self.path / ROUNDS).glob("*.pt") if p.stem.isdigit())

    def load_views(self, data_dir: str | Path, width: int | None) -> Views:
        """The robot's views as its daemon trains on them: at ``width``; images only: through this run's SfM."""
        from agent.data.loaders import load_views

        return load_views(data_dir, width=width, sfm_cache_dir=self.sfm_cache)

    def save(self, ck: RobotCheckpoint) -> None:
        _atomic_torch_save({"round": ck.round, "robot_id": ck.robot_id, "trainer": ck.trainer,
                            "elected": ck.elected, "training": ck.training,
                            "box_from_shared": ck.box_from_shared, "signature": ck.signature}, self.checkpoint)

    def save_round(self, round_index: int, trainer: RobotTrainer) -> None:
        (self.path / ROUNDS).mkdir(exist_ok=True)
        snap = {"round": round_index, "field": trainer.field.state_dict(), "grid": trainer.grid.state_dict(),
                "pose": trainer.pose.state_dict()}
        _atomic_torch_save(snap, self.round_path(round_index))

    def load(self, device: torch.device | str = "cpu") -> RobotCheckpoint | None:
        """The checkpoint, or None if there is none."""
        if not self.checkpoint.is_file():
            return None
        state = torch.load(self.checkpoint, map_location=device, weights_only=False)
        return RobotCheckpoint(round=int(state["round"]), robot_id=int(state["robot_id"]), trainer=state["trainer"],
                               elected=bool(state.get("elected", False)), training=state["training"],
                               box_from_shared=state["box_from_shared"], signature=state.get("signature", ""))

    def write_done(self, robot_id: int, rounds: int, rejected: dict[str, int]) -> None:
        done = {"robot": robot_id, "rounds": rounds, "time": time.time(), "rejected": rejected}
        self.done.write_text(json.dumps(done, indent=2) + "\n")


def load_for_eval(run_dir: str | Path, data_dir: str | Path, round: int | None = None) -> RobotTrainer:
    """Rebuild a robot's trainer from its run folder (final checkpoint or ``rounds/<k>.pt``)."""
    folder = RunFolder(run_dir, create=False)
    ck = folder.load()
    if ck is None:
        raise FileNotFoundError(f"{folder.checkpoint}: no checkpoint")
    training = ck.training
    views = folder.load_views(data_dir, training.image_width)
    trainer = build_robot(ck.robot_id, views, ck.box_from_shared, training).trainer
    trainer.load_state_dict(ck.trainer)
    if round is not None:
        snap = torch.load(folder.round_path(round), map_location="cpu", weights_only=False)
        trainer.field.load_state_dict(snap["field"])
        trainer.grid.load_state_dict(snap["grid"])
        trainer.pose.load_state_dict(snap["pose"])
    return trainer
