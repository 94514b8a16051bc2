"""A finished swarm run scored round by round: every robot's kept snapshots on the held-out views.

Per robot and per scored round k (``rounds/<k>.safetensors``, rebuilt by ``agent.checkpoint.load_for_eval``):
PSNR/SSIM on all held-out views and on those only other robots saw, the pose error against the
truth, and the consensus disagreement ``||theta_i - mean|| / ||mean||`` among the robots that
have a snapshot of that round. A robot's final snapshot is also scored the costly ways (each
held-out pose fitted to its image, the truth's intrinsics, its own training views).

Robots with images only train in their own SfM frames: each frame is fitted to the world on the
robot's cameras before anything is scored (:func:`calibrate_frames`); a robot whose frame cannot
be fitted is not scored, and none is when the reference's cannot (it defines the shared frame).
"""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from agent.checkpoint import RunFolder, load_for_eval, load_robot
from agent.consensus import disagreement
from agent.data.split import robot_folder
from agent.data.views import DataError
from agent.evaluation.evalset import EvalSet
from agent.evaluation.scores import ImageScores, RobotEval, evaluate_robot
from agent.progress import track
from agent.swarm import RobotSetup
from agent.trainer import RobotTrainer

__all__ = ["SwarmRun", "ScoringOptions", "RoundScores", "RunScores", "score_run", "calibrate_frames"]

Echo = Callable[[str], None]


def silent(_: str) -> None:
    """The default ``echo`` of the evaluation: progress goes nowhere."""


@dataclass(frozen=True)
class SwarmRun:
    """Where a swarm run is on disk: the split it trained on and each robot's run folder."""

    split_dir: Path  # written by agent.data.split.write_split: robot<i>/, eval/, truth.json, scene.json
    run_dirs: dict[int, Path]  # robot id -> its run folder (agent.checkpoint.RunFolder)
    data_dirs: dict[int, Path] | None = None  # robot id -> its recording, when not the split's robot<i>/
    _views: dict = field(default_factory=dict, compare=False, repr=False)  # robot id -> its views, read once

    @property
    def ids(self) -> list[int]:
        return list(self.run_dirs)

    def folder(self, robot_id: int) -> RunFolder:
        return RunFolder(self.run_dirs[robot_id], create=False)

    def data_dir(self, robot_id: int) -> Path:
        if self.data_dirs is not None and robot_id in self.data_dirs:
            return self.data_dirs[robot_id]
        return robot_folder(self.split_dir, robot_id)

    def load(self, robot_id: int, round: int | None = None) -> RobotTrainer:
        """The robot's trainer as it was after ``round`` (default: its last checkpoint)."""
        return load_for_eval(self.run_dirs[robot_id], self.data_dir(robot_id), round=round)

    def load_setup(self, robot_id: int, round: int | None = None) -> RobotSetup:
        """As :meth:`load`, with its own held-out views; the robot's views are read once per run."""
        if robot_id not in self._views:
            ck = self.folder(robot_id).load()
            width = ck.training.image_width if ck is not None else None
            self._views[robot_id] = self.folder(robot_id).load_views(self.data_dir(robot_id), width)
        return load_robot(self.run_dirs[robot_id], self.data_dir(robot_id), round=round, views=self._views[robot_id])

    def snapshot_rounds(self) -> dict[int, list[int]]:
        return {i: self.folder(i).snapshot_rounds() for i in self.ids}


@dataclass(frozen=True)
class ScoringOptions:
    """What is scored: the plain scores on every scored round, the costly ones on final snapshots only."""

    every: int = 1  # score every k-th round's snapshot (and always the last round)
    with_ssim: bool = True
    fit_pose_steps: int = 0  # final snapshot: each held-out view's pose fitted to its image first (0 = off)
    own_views_every: int = 0  # final snapshot: also every k-th own training view (0 = off)


_FINAL_ONLY = ("psnr_pose_fitted", "psnr_true_intrinsics", "psnr_own_views", "disagreement")


@dataclass
class RoundScores(ImageScores):
    """One robot's snapshot of one round against the truth."""

    rotation_error_deg: float | None
    translation_error: float | None  # scene units
    scale_error_rel: float | None
    psnr_pose_fitted: float | None = None  # this and the next two: final snapshot only, when asked
    psnr_true_intrinsics: float | None = None
    psnr_own_views: float | None = None
    disagreement: float | None = None  # with >= 2 robots scored on this round

    @classmethod
    def of(cls, ev: RobotEval, with_ssim: bool, **more) -> "RoundScores":
        extra = ev.summary()
        return super().of(ev, with_ssim, rotation_error_deg=ev.pose.get("rotation_deg"),
                          translation_error=ev.pose.get("translation"), scale_error_rel=ev.pose.get("scale_rel"),
                          **{k: extra.get(k) for k in _FINAL_ONLY[:3]}, **more)

    def to_dict(self) -> dict:
        """As report.json has it: the final-only scores only where they were computed."""
        return {k: v for k, v in super().to_dict().items() if v is not None or k not in _FINAL_ONLY}


@dataclass
class RunScores:
    evalset: EvalSet  # images-only robots' frames calibrated
    rounds: dict[int, dict[int, RoundScores]]  # robot -> round -> scores, rounds in order
    finals: dict[int, RobotTrainer]  # robot -> the model of its final snapshot (when that round was scored)
    notes: list[str]  # what could not be scored, and why

    def final_round(self, robot_id: int) -> int | None:
        return max(self.rounds[robot_id]) if self.rounds[robot_id] else None

    def final(self, robot_id: int) -> RoundScores | None:
        k = self.final_round(robot_id)
        return None if k is None else self.rounds[robot_id][k]


def rounds_to_score(snapshots: dict[int, list[int]], every: int) -> list[int]:
    """Every ``every``-th round any robot kept, and the last one."""
    rounds = sorted({k for ks in snapshots.values() for k in ks})
    return [k for k in rounds if k % every == 0 or k == rounds[-1]]


def score_run(run: SwarmRun, opts: ScoringOptions, echo: Echo = silent, workers: int = 1) -> RunScores:
    """Score every robot's snapshot of every chosen round (see the module docstring).

    ``workers`` > 1: the snapshots are scored in that many processes (one thread each), the same
    scores in a fraction of the wall time where there are cores for them."""
    evalset = EvalSet.from_dir(run.split_dir)
    snaps = run.snapshot_rounds()
    notes = calibrate_frames(evalset, run, snaps, echo) if evalset.needs_calibration else []
    evaluable = {i for i in run.ids if evalset.has_frame(i)} if evalset.has_frame(evalset.reference_id) else set()
    chosen = rounds_to_score(snaps, opts.every)
    jobs = [(i, k, k == snaps[i][-1]) for k in chosen for i in run.ids if k in snaps[i] and i in evaluable]
    echo(f"evaluating {len(chosen)} rounds x {len(run.ids)} robots on {len(evalset.views)} held-out views"
         + (f" ({workers} worker processes)" if workers > 1 and len(jobs) > 1 else ""))
    for i in sorted({i for i, _, final in jobs if final and opts.fit_pose_steps}):
        echo(f"robot {i}: fitting each held-out view's pose to its image ({opts.fit_pose_steps} steps each)")
    done: dict[tuple[int, int], RoundScores] = {}
    thetas: dict[int, dict[int, list]] = {k: {} for k in chosen}  # a round's models, until all are scored
    waiting = {k: sum(job[1] == k for job in jobs) for k in chosen}

    def scored(i: int, k: int, result: tuple[RoundScores, list]) -> None:
        done[i, k], thetas[k][i] = result
        waiting[k] -= 1
        if waiting[k] == 0:  # the round's disagreement, then its models are let go
            models = thetas.pop(k)
            if len(models) >= 2:
                order = sorted(models)  # in robot order, whichever finished first: the same sums
                for j, d in zip(order, disagreement([models[j] for j in order])):
                    done[j, k].disagreement = d

    description = f"evaluating {len(run.ids)} robots"
    if workers > 1 and len(jobs) > 1:
        ctx = mp.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
            futures = {pool.submit(_score_job, run, evalset, i, k, final, opts): (i, k) for i, k, final in jobs}
            for f in track(as_completed(futures), description, total=len(futures)):
                scored(*futures.pop(f), f.result())
    else:
        for i, k, final in track(jobs, description):
            scored(i, k, _score_job(run, evalset, i, k, final, opts))
    scores = RunScores(evalset, {i: {} for i in run.ids}, {}, notes)
    for k in chosen:  # rounds in order
        for i in run.ids:
            if (i, k) in done:
                scores.rounds[i][k] = done[i, k]
    for i, k, final in jobs:
        if final:
            scores.finals[i] = run.load(i, round=k)
    return scores


def _score_job(run: SwarmRun, evalset: EvalSet, robot_id: int, round_index: int, final: bool,
               opts: ScoringOptions) -> tuple[RoundScores, list]:
    """One robot's snapshot of one round, scored (in a worker process or here) -> (scores, its theta)."""
    if mp.parent_process() is not None:
        torch.set_num_threads(1)
    trainer = run.load(robot_id, round=round_index)
    fit_steps = opts.fit_pose_steps if final else 0  # costly: the final model only
    ev = evaluate_robot(trainer, evalset, robot_id, with_ssim=opts.with_ssim, pose_fit_steps=fit_steps,
                        compare_true_intrinsics=final, own_views_every=opts.own_views_every if final else 0)
    return RoundScores.of(ev, opts.with_ssim), [t for _, t in sorted(trainer.theta().items())]


def calibrate_frames(evalset: EvalSet, run: SwarmRun, snapshots: dict[int, list[int]],
                     echo: Echo = silent) -> list[str]:
    """Fit every images-only robot's SfM frame to the world; returns notes on those that could not be.

    The cameras are those of the robot's trainer as ``load_for_eval`` rebuilds it, i.e. its SfM
    frame exactly as it trained in, whatever the daemon did to the SfM's output.
    """
    notes = ["images only: each robot's local frame is its own SfM; it is aligned to the world by a Sim(3) fit "
             "of its camera centres to the true ones before scoring (see 'Evaluation frames')"]
    for i in sorted(evalset.cameras_world):
        if not snapshots.get(i):
            notes.append(f"robot {i}: no snapshot, so no SfM frame to calibrate: not evaluated")
            continue
        try:
            cal = evalset.calibrate(i, run.load(i).refined_views())  # its cameras as it refined them
        except (DataError, OSError) as e:
            notes.append(f"robot {i}: its SfM frame could not be calibrated ({e}): not evaluated")
            continue
        echo(f"robot {i}: SfM frame calibrated on {cal.inliers}/{cal.matched} cameras, centre error "
             f"{cal.centre_error_median:.4f}, rotation error {cal.rotation_error_median_deg:.3f} deg (medians)")
    if not evalset.has_frame(evalset.reference_id):
        notes.append(f"the reference (robot {evalset.reference_id}) has no calibrated frame, so the shared frame is "
                     "unknown: no robot could be evaluated")
    return notes
