"""Evaluation against the truth of a split: of one robot, and of a whole swarm run round by round.

::

    evalset.py    the held-out views and the truth: each robot's frame in the world (SfM frames calibrated)
    scores.py     one robot's field on the held-out views in the shared frame, and its pose error
    run.py        a finished run folder scored round by round (snapshots, disagreement)
    baselines.py  the points of comparison: the centralised model on every view, each robot alone
    summary.py    a scored run in a few numbers: mean scores, gap to centralised, gain over alone

Only this package reads the truth; the CLI's report formats what it returns.
"""

from agent.evaluation.baselines import (
    AloneScores,
    BaselineFailure,
    BaselineRun,
    Baselines,
    CentralisedScores,
    evaluate_heldout,
    run_baselines,
    train_alone,
    train_baseline,
    train_centralised,
)
from agent.evaluation.evalset import EvalSet, FrameCalibration, calibrate_frame
from agent.evaluation.run import RoundScores, RunScores, ScoringOptions, SwarmRun, calibrate_frames, score_run
from agent.evaluation.scores import ImageScores, RobotEval, evaluate_robot, fit_view_pose
from agent.evaluation.summary import BaselineGaps, RunSummary, summarise

__all__ = [
    "EvalSet", "FrameCalibration", "calibrate_frame",
    "ImageScores", "RobotEval", "evaluate_robot", "fit_view_pose",
    "SwarmRun", "ScoringOptions", "RoundScores", "RunScores", "score_run", "calibrate_frames",
    "BaselineRun", "train_baseline", "evaluate_heldout",
    "CentralisedScores", "AloneScores", "BaselineFailure", "Baselines", "train_centralised", "train_alone",
    "run_baselines",
    "BaselineGaps", "RunSummary", "summarise",
]
