"""The points of comparison of a swarm: the centralised model, and each robot alone.

The centralised model is trained on every robot's views with the true poses: the paper's point
of comparison, and the same :class:`RobotTrainer` as a swarm robot (pose fixed, no neighbours),
so the comparison measures the distribution, not two codebases. Held-out views follow the
split's rule (indices 0, k, 2k, ...), so the baseline and a split of the same dataset are scored
on the same views.

"Alone" is one robot trained on its own views only, with its pose fixed to the truth: an upper
bound for a robot without neighbours, since it gets the frame for free (images only: its
calibrated SfM frame, and the split's field box). For a finished run (:func:`run_baselines`)
both get the same steps as each robot; the robots alone train in worker processes meanwhile.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from agent.data.folder import read_scene
from agent.data.loaders import load_views
from agent.data.split import estimate_scene_box, test_indices
from agent.data.views import DataError, Views
from agent.evaluation.evalset import EvalSet
from agent.evaluation.run import Echo, SwarmRun, silent
from agent.evaluation.scores import ImageScores, evaluate_robot
from agent.geometry import box_from_center, transform_c2w
from agent.metrics import finite_mean
from agent.swarm import SwarmTrainingConfig, build_robot, own_holdout_split
from agent.trainer import RobotTrainer, TrainConfig


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
    test_every: int = 8,
    on_step: Callable[[int], None] | None = None,
) -> BaselineRun:
    """Train on all views but the held-out ones, in the dataset's own (world) frame."""
    test = test_indices(len(views), test_every)
    train = [i for i in range(len(views)) if i not in set(test)]
    if not train:
        raise DataError(f"no training views left: {len(views)} views, every {test_every}th a test view")
    center, half, source = estimate_scene_box(views, cfg.field.unbounded)  # for the field it trains
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
def evaluate_heldout(run: BaselineRun, views: Views, with_ssim: bool = True,
                     renders: list | None = None) -> dict[str, list[float]]:
    """PSNR/SSIM (white background) on the held-out views, in the world frame."""
    return run.trainer.evaluate(views.subset(run.test_indices), frame="local", with_ssim=with_ssim, renders=renders)


@dataclass
class CentralisedScores:
    """The centralised model on the held-out views, in the world frame."""

    psnr: float | None  # mean over the held-out views
    ssim: float | None
    seconds: float
    views: int  # held-out views scored
    renders: np.ndarray | None = field(default=None, repr=False)  # [V, H, W, 3] uint8: its render of each view
    field_parameters: int | None = None  # of its field: the robots' own count, or it is another model

    def to_dict(self) -> dict:
        return {"psnr": self.psnr, "ssim": self.ssim, "seconds": self.seconds, "views": self.views,
                "field_parameters": self.field_parameters}


def _field_parameters(trainer: RobotTrainer) -> int:
    return sum(p.numel() for p in trainer.field.parameters())


def _uint8(renders: list) -> np.ndarray:
    return np.stack([np.round(np.clip(r.numpy(), 0, 1) * 255).astype(np.uint8) for r in renders])


@dataclass
class AloneScores(ImageScores):
    """One robot alone, scored as the swarm's robots are (shared frame, others-only views)."""

    seconds: float


@dataclass
class BaselineFailure:
    """A baseline that raised: it must not take the swarm's report with it."""

    error: str  # "<exception type>: <message>"

    def to_dict(self) -> dict:
        return {"error": self.error}


@dataclass
class Baselines:
    steps: int  # of each baseline model (the report gives it as many as each robot trained)
    centralised: CentralisedScores
    alone: dict[int, AloneScores | BaselineFailure] | None = None  # None: not asked for

    def to_dict(self) -> dict:
        doc = {"steps": self.steps, "centralised": self.centralised.to_dict()}
        if self.alone is not None:
            doc["alone"] = {str(i): a.to_dict() for i, a in self.alone.items()}
        return doc


def train_centralised(dataset: str, width: int | None, training: SwarmTrainingConfig, test_every: int,
                      steps: int, with_ssim: bool = True) -> CentralisedScores:
    """The centralised model on ``dataset`` at ``width``, scored on its views held out by the split's rule."""
    t = time.monotonic()
    views = load_views(dataset, width=width)
    # true poses: the robots' camera refinement (for SfM cameras) has nothing to correct here
    cfg = replace(training.train, total_steps=steps, seed=training.seed, init_seed=training.seed,
                  cameras=replace(training.train.cameras, enabled=False))
    run = train_baseline(views, cfg, test_every)
    renders: list = []
    scores = evaluate_heldout(run, views, with_ssim=with_ssim, renders=renders)
    return CentralisedScores(psnr=finite_mean(scores["psnr"]), ssim=finite_mean(scores["ssim"]),
                             seconds=time.monotonic() - t, views=len(scores["psnr"]), renders=_uint8(renders),
                             field_parameters=_field_parameters(run.trainer))


def swarm_box(run: SwarmRun, reference_id: int) -> torch.Tensor | None:
    """The field box the swarm trained in (the reference's checkpoint's; [4, 4] float64), or None."""
    ck = run.folder(reference_id).load(reference_id)
    return None if ck is None else ck.box_from_shared.double()


def robots_kept_views(run: SwarmRun, training: SwarmTrainingConfig, frame_from_local: Callable[[int], torch.Tensor]
                      ) -> Views:
    """Every robot's training frames (a bag's keyframes, its own held-out frames excepted), carried
    into one frame by ``frame_from_local(i)`` ([4, 4] float64 for robot i)."""
    parts = []
    for i in run.ids:
        views, _ = own_holdout_split(run.folder(i).load_views(run.data_dir(i), training.image_width),
                                     training.own_holdout_every)
        c2w = transform_c2w(frame_from_local(i), views.c2w.double()).float()
        parts.append(Views(views.images, c2w, views.intrinsics, [f"robot{i}/{n}" for n in views.names]))
    return Views(torch.cat([p.images for p in parts]), torch.cat([p.c2w for p in parts]),
                 torch.cat([p.intrinsics for p in parts]), [n for p in parts for n in p.names])


def train_centralised_on_robots(run: SwarmRun, training: SwarmTrainingConfig, steps: int,
                                with_ssim: bool = True) -> CentralisedScores:
    """The centralised model on exactly the frames the robots trained on (a bag's keyframes, their own
    held-out frames excepted), each carried into the swarm's shared frame by the truth, in the field box
    the swarm used (the reference's), scored on the split's held-out views: robots that record choose
    their own frames, so the dataset's views are not theirs. The swarm's frame and box, not the world's:
    a turn of the frame alone moves a model's score by about a dB (benchmarks/bench_frame.py), which
    would otherwise enter the comparison."""
    t = time.monotonic()
    evalset = EvalSet.from_dir(run.split_dir)
    views = robots_kept_views(run, training, evalset.T_shared_from_local)
    cfg = replace(training.train, total_steps=steps, seed=training.seed, init_seed=training.seed,
                  cameras=replace(training.train.cameras, enabled=False))
    box = swarm_box(run, evalset.reference_id)
    if box is None:  # no checkpoint of the reference: a box of these views
        center, half, _ = estimate_scene_box(views, cfg.field.unbounded)
        box = box_from_center(center, half)
    trainer = RobotTrainer(views, replace(cfg, pose=replace(cfg.pose, mode="fixed")), box)
    trainer.train(steps)
    renders: list = []
    held_out = Views(evalset.views.images, evalset.shared_cameras(), evalset.shared_intrinsics(), evalset.views.names)
    scores = trainer.evaluate(held_out, frame="local", with_ssim=with_ssim, renders=renders)
    return CentralisedScores(psnr=finite_mean(scores["psnr"]), ssim=finite_mean(scores["ssim"]),
                             seconds=time.monotonic() - t, views=len(scores["psnr"]), renders=_uint8(renders),
                             field_parameters=_field_parameters(trainer))


def train_alone(run: SwarmRun, robot_id: int, training: SwarmTrainingConfig, steps: int,
                with_ssim: bool = True) -> AloneScores:
    """One robot of ``run`` alone on its own views, pose fixed to the truth (in a worker process: 1 thread).

    Images only: the robot's SfM frame (and the reference's, which defines the shared frame) is
    calibrated here on the views as this process loads them, so the truth fits those views.
    """
    torch.set_num_threads(1)
    t = time.monotonic()
    evalset = EvalSet.from_dir(run.split_dir)
    scene = read_scene(run.split_dir)

    def own_views(i: int) -> Views:
        return run.folder(i).load_views(run.data_dir(i), training.image_width)

    views = own_views(robot_id)
    if evalset.needs_calibration:
        evalset.calibrate(robot_id, views)
        if robot_id != evalset.reference_id:
            evalset.calibrate(evalset.reference_id, own_views(evalset.reference_id))
    box = scene.box_from_shared if scene.box_from_shared is not None else evalset.box_from_shared
    setup = build_robot(robot_id, views, box, replace(training, rounds=1, steps_per_round=steps),
                        initial_pose=evalset.T_shared_from_local(robot_id).float(),
                        is_reference=True)  # is_reference: the pose stays frozen at the truth
    setup.trainer.train(steps)
    # its field is built in its own calibrated SfM frame, so it is seen through its own camera
    ev = evaluate_robot(setup.trainer, evalset, robot_id, with_ssim=with_ssim, camera_of=robot_id)
    return AloneScores.of(ev, with_ssim, seconds=time.monotonic() - t)


def run_baselines(run: SwarmRun, *, dataset: str, width: int | None, training: SwarmTrainingConfig,
                  test_every: int, steps: int, alone: bool = True, with_ssim: bool = True,
                  echo: Echo = silent, on_robots_frames: bool = False, workers: int = 2) -> Baselines:
    """Centralised model here; the robots alone in ``workers`` worker processes meanwhile, one thread each
    (2 cores: ~half the wall time). Without them the centralised model takes the ``workers`` cores as
    threads, rather than one thread beside idle cores.

    on_robots_frames: the centralised model on the frames the robots chose (recordings), not the dataset's."""
    pool = None
    futures = {}
    if alone:
        n = min(workers, len(run.ids))
        echo(f"baseline: robots {run.ids} alone, {steps} steps each ({n} worker processes)")
        pool = ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"))
        futures = {i: pool.submit(train_alone, run, i, training, steps, with_ssim) for i in run.ids}
    threads = torch.get_num_threads()
    try:
        if not futures:
            torch.set_num_threads(max(threads, workers))
        echo(f"baseline: centralised model, {steps} steps" + (" on the robots' kept frames" if on_robots_frames else "")
             + f" ({torch.get_num_threads()} threads)")
        central = (train_centralised_on_robots(run, training, steps, with_ssim) if on_robots_frames
                   else train_centralised(dataset, width, training, test_every, steps, with_ssim))
        result = Baselines(steps, central)
        if futures:
            result.alone = {}
            for i, f in futures.items():
                try:
                    result.alone[i] = f.result()
                except Exception as e:  # a baseline that fails must not take the swarm's report with it
                    echo(f"baseline: robot {i} alone failed: {type(e).__name__}: {e}")
                    result.alone[i] = BaselineFailure(f"{type(e).__name__}: {e}")
    finally:
        torch.set_num_threads(threads)
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    return result
