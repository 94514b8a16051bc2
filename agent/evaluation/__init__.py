"""Evaluation against the truth of a split, of one robot and of a whole swarm run.

::

    evalset.py    the held-out views and the truth: each robot's frame in the world (SfM frames calibrated)
    scores.py     one robot's field on the held-out views in the shared frame, and its pose error
    baselines.py  the points of comparison: the centralised model on every view, true poses
"""

from agent.evaluation.baselines import BaselineRun, evaluate_heldout, holdout_indices, train_baseline
from agent.evaluation.evalset import EvalSet, FrameCalibration, calibrate_frame
from agent.evaluation.scores import RobotEval, evaluate_robot, fit_view_pose

__all__ = [
    "EvalSet", "FrameCalibration", "calibrate_frame",
    "RobotEval", "evaluate_robot", "fit_view_pose",
    "BaselineRun", "train_baseline", "evaluate_heldout", "holdout_indices",
]
