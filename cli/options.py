"""Pieces shared by several commands: help texts, config loading, threads, progress bars."""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import Iterator

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from cli.config import ConfigError, apply_overrides, from_dict, load_toml, merge_tables, overrides_table
from cli.errors import UserError

DATA_HELP = ("Dataset: a folder (transforms.json, COLMAP sparse/0, images), a json file, a ROS 2 bag (rosbag2 folder, "
             ".mcap, .db3), or procedural[:views=100,width=64,seed=0].")
RUN_HELP = "A run folder: a scenario's --out (robots/<id>/ + data/), up's runs/<swarm>/, or one robot's --run-dir."
RUN_DATA_HELP = ("The robots' data folder (a split folder with robot<i>/ inside, or one robot's folder), for run "
                 "folders that do not record it (an older dinerf's); given, it wins over the record.")
SET_HELP = "Override a setting, e.g. --set optim.lr=5e-3 (repeatable)."


def set_threads(threads: int) -> None:
    import torch

    if threads < 1:
        raise ConfigError("--threads must be >= 1")
    torch.set_num_threads(threads)


def check_output_folder(path: Path, option: str) -> None:
    """A file where a command will write its folder is the user's mistake: say so in one line."""
    if path.exists() and not path.is_dir():
        raise UserError(f"{option} {path}: exists and is not a folder")


def load_train_config(path: Path | None, overrides: list[str], total_steps: int | None = None, capture=None):
    """TrainConfig from the [train] table of a TOML file (if any), then --set overrides, over what the
    ``capture`` calls for (``agent.defaults``; None: the dataclass defaults)."""
    from agent.defaults import fit_train
    from agent.trainer import TrainConfig

    if total_steps is not None and total_steps < 1:
        raise ConfigError(f"--steps must be >= 1, got {total_steps}")
    data = load_toml(path).get("train", {}) if path else {}
    cfg = from_dict(TrainConfig, data, "train")
    if total_steps is not None:
        cfg = dataclasses.replace(cfg, total_steps=total_steps)
    cfg = apply_overrides(cfg, overrides)  # checks every key before the capture fills the rest
    if capture is None:
        return cfg
    given = merge_tables(data, overrides_table(overrides))
    return dataclasses.replace(from_dict(TrainConfig, fit_train(given, capture), "train"), total_steps=cfg.total_steps)


def progress_bar() -> Progress:
    return Progress(
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=False,
    )


class _RichListener:
    """agent.progress's listener drawn as rich bars (a spinner-like bar for steps of unknown length)."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress

    def begin(self, description: str, total: int | None) -> object:
        return self.progress.add_task(description, total=total)

    def advance(self, task: object) -> None:
        self.progress.advance(task)

    def end(self, task: object) -> None:
        t = next(x for x in self.progress.tasks if x.id == task)
        done = t.completed if t.total is None else t.total  # a spinner ends full, at what it did
        self.progress.update(task, total=done, completed=done)


@contextlib.contextmanager
def progress_listener(enabled: bool | None = None) -> Iterator[None]:
    """Bars on stderr for the long local work inside the block (image loading, SfM, evaluation);
    by default only on a terminal (a log file gets no bars)."""
    import sys

    from rich.console import Console

    from agent.progress import listening

    if not (sys.stderr.isatty() if enabled is None else enabled):
        yield
        return
    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=Console(stderr=True), transient=True) as progress:
        with listening(_RichListener(progress)):
            yield
