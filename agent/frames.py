"""Which frames a swarm's robots are in, and the pose settings that follow from it.

A robot whose poses are in its own frame must learn where that frame lies in the shared one;
left at the identity it trains a field in the wrong place and pulls its neighbours' towards it,
while its log says "0 deg". So the swarm file says which frames its robots are in, and the
defaults follow:

- ``shared``: every robot's poses are in one frame (a capture with known poses): the pose
  stays fixed, the start is the identity;
- ``local``: each robot in its own metric frame (its odometry): SE(3) poses learnt from a
  coarse start (keyframe summaries matched with a neighbour's);
- ``sfm``: each robot has images only and runs its own SfM, whose frame has its own scale:
  Sim(3) poses from a coarse start.

Settings given explicitly win, unless they contradict the frames (then a clear error).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from agent.daemon import DaemonConfig
from agent.swarm import SwarmTrainingConfig

__all__ = ["Frames", "FRAMES", "frames_of_split", "resolve_pose_settings"]

Frames = Literal["shared", "local", "sfm"]
FRAMES = ("shared", "local", "sfm")
_DEFAULTS = {"shared": ("identity", "fixed"), "local": ("coarse", "se3"), "sfm": ("coarse", "sim3")}


def frames_of_split(frame: str, images_only: bool) -> Frames:
    """The frames of robots written by a split (``SplitConfig.frame``, ``images_only``)."""
    if images_only:
        return "sfm"
    return "shared" if frame == "world" else "local"


def resolve_pose_settings(frames: Frames, training: SwarmTrainingConfig,
                          daemon: DaemonConfig) -> tuple[SwarmTrainingConfig, DaemonConfig]:
    """Fill the unset initial pose and pose model from the frames; refuse what contradicts them."""
    if frames not in FRAMES:
        raise ValueError(f"swarm.frames must be one of {list(FRAMES)}, got {frames!r}")
    initial_default, mode_default = _DEFAULTS[frames]
    initial = daemon.initial_pose if daemon.initial_pose is not None else initial_default
    mode = training.train.pose.mode if training.train.pose.mode is not None else mode_default
    if frames == "local" and initial == "identity" and mode == "fixed":
        raise ValueError("swarm.frames = \"local\" but the pose stays fixed at the identity "
                         "(daemon.initial_pose = \"identity\", training.train.pose.mode = \"fixed\"): every robot would "
                         "train in its own frame as if it were the shared one; unset them, or learn the pose")
    if frames == "sfm" and (initial != "coarse" or mode != "sim3"):
        raise ValueError("swarm.frames = \"sfm\" (robots with their own SfM, each with its own scale) needs "
                         "daemon.initial_pose = \"coarse\" and training.train.pose.mode = \"sim3\" (got "
                         f"{initial!r}, {mode!r}); unset them to get these")
    pose = dataclasses.replace(training.train.pose, mode=mode)
    training = dataclasses.replace(training, train=dataclasses.replace(training.train, pose=pose))
    return training, dataclasses.replace(daemon, initial_pose=initial)
