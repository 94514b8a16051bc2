"""Evaluation against the truth of a split, of one robot and of a whole swarm run.

::

    evalset.py    the held-out views and the truth: each robot's frame in the world (SfM frames calibrated)
    scores.py     one robot's field on the held-out views in the shared frame, and its pose error
    run.py        a finished run folder scored round by round (snapshots, disagreement)
    baselines.py  the points of comparison: the centralised model on every view, true poses
"""

from agent.evaluation.baselines import BaselineRun, evaluate_heldout, holdout_indices, train_baseline
from agent.evaluation.evalset import EvalSet, FrameCalibration, calibrate_frame
from agent.evaluation.run import RoundScores, RunScores, ScoringOptions, SwarmRun, calibrate_frames, score_run
from agent.evaluation.scores import ImageScores, RobotEval, evaluate_robot, fit_view_pose

__all__ = [
    "EvalSet", "FrameCalibration", "calibrate_frame",
    "ImageScores", "RobotEval", "evaluate_robot", "fit_view_pose",
    "SwarmRun", "ScoringOptions", "RoundScores", "RunScores", "score_run", "calibrate_frames",
    "BaselineRun", "train_baseline", "evaluate_heldout", "holdout_indices",
]
