"""Held-out scores of a run folder, per robot and per view, through agent.evaluation.

Nothing is scored here that the scenario report does not score the same way: the held-out
set and truth are :class:`agent.evaluation.EvalSet`, images-only robots' frames are calibrated
by :func:`agent.evaluation.calibrate_frames`, and each robot is scored by
:func:`agent.evaluation.evaluate_robot` in the shared frame. This module only picks the robots
and the round, and lays the per-view numbers out.
"""

from __future__ import annotations

from typing import Callable

from agent.data.views import DataError
from agent.evaluation import EvalSet, calibrate_frames, evaluate_robot
from agent.runs import Run

__all__ = ["score_heldout"]


def score_heldout(run: Run, robots: list[int], round: int | None = None, with_ssim: bool = True,
                  device: str | None = None, echo: Callable[[str], None] = lambda _: None) -> dict:
    """PSNR/SSIM of each robot's field on the split's held-out views.

    -> {"views": [names], "notes": [...], "robots": {id: {summary..., "per_view": [{view, psnr, ssim, others_only}]}}}
    """
    swarm = run.swarm_run()
    evalset = EvalSet.from_dir(swarm.split_dir)
    notes: list[str] = []
    if evalset.needs_calibration:
        notes = calibrate_frames(evalset, swarm, swarm.snapshot_rounds(), echo)
    doc: dict = {"views": list(evalset.views.names), "notes": notes, "round": round, "robots": {}}
    scorable = [i for i in robots if evalset.has_frame(i)]
    if not scorable:
        raise DataError(f"no robot of {robots} has a frame known to the truth of {swarm.split_dir} "
                        f"({'; '.join(notes) or 'not in truth.json'})")
    notes += [f"robot {i}: its frame is unknown to the truth: not scored" for i in robots if i not in scorable]
    for i in scorable:
        echo(f"robot {i}: rendering {len(evalset.views)} held-out views")
        ev = evaluate_robot(run.load(i, round=round, device=device), evalset, i, with_ssim=with_ssim)
        others = set(ev.others_only)
        per_view = [{"view": name, "psnr": ev.psnr[k], "ssim": ev.ssim[k] if with_ssim else None,
                     "others_only": k in others} for k, name in enumerate(evalset.views.names)]
        summary = {k: v for k, v in ev.summary().items() if with_ssim or not k.startswith("ssim")}
        doc["robots"][i] = {**summary, "per_view": per_view}
    return doc


def score_own_frames(run: Run, robots: list[int], round: int | None = None, with_ssim: bool = True,
                     device: str | None = None, echo: Callable[[str], None] = lambda _: None) -> dict | None:
    """Every robot's field on every robot's own held-out frames through the estimated poses
    (:mod:`agent.evaluation.cross`); None when no robot kept frames out (``own_holdout_every = 0``)."""
    from agent.evaluation.cross import score_cross

    setups = {i: run.load_setup(i, round=round, device=device) for i in robots}
    holdouts = {i: s.holdout for i, s in setups.items() if s.holdout is not None}
    if not holdouts:
        return None
    echo(f"robots {robots}: rendering each other's held-out frames ({sum(len(v) for v in holdouts.values())} frames)")
    cross = score_cross({i: s.trainer for i, s in setups.items()}, holdouts, with_ssim=with_ssim,
                        run_dirs={i: run.robots[i].run_dir for i in robots})
    return cross.to_dict()
