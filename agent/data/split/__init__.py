"""Turn one posed dataset into N robots the way the Di-NeRF paper does, plus the evaluation truth.

Each robot gets the views of one sector of directions around the scene centre (``by = "sector"``)
or one stretch of the capture (``by = "trajectory"``), re-expressed in its own local frame;
held-out views of the whole scene (in the world frame) are kept for evaluation; the true
relative poses go to a file that only evaluation reads.

Sectors. The azimuth of a camera is the angle of its centre about the up axis through the
scene centre (up: given, or the mean camera up vector; centre: given, or the least-squares
point closest to all optical axes). When the cameras surround the scene (``circle``: no gap
between neighbouring training azimuths wider than half a sector, ``w / 2`` with ``w = 360 / N``),
robot k (k = 0..N-1, in id order) owns the core sector ``[start + k w, start + (k + 1) w)``,
``start = sector_start_deg``. Otherwise the cameras cover an ``arc`` (a handheld capture round part
of the scene), and equal sectors would leave robots empty-handed: the core sectors are cut at the
k/N quantiles of the training azimuths along the arc (halfway between the two views a cut
separates), so each robot owns 1/N of the training views, and the end sectors reach halfway
into the empty arc (``sector_start_deg`` plays no part). Every sector is widened by a margin
``delta`` on both sides, so robot k holds the training views whose azimuth falls in
``[start_k - delta, end_k + delta)``.

Overlap, precisely: the overlap of robot i is the fraction of robot i's training views that
also belong to at least one other robot. For azimuths spread uniformly it is
``4 delta / (w + 2 delta)``; rather than trust that, ``delta`` is chosen on the actual views
(among all values at which a view enters a neighbour's sector, below half the narrowest sector)
so that the mean over robots of the achieved overlap is closest to the requested one. The
achieved per-robot and mean overlaps are reported.

Trajectory: what robots record is a path, not a sector. The training views, in the source order
(the capture order), are cut into N contiguous segments of (nearly) equal length, robot k owning
the k-th; the overlap is shared views at the segment borders: the ``s`` views round each cut
(``s // 2`` before it, the rest after) belong to both neighbours, ``s`` (fewer than the shortest
segment) chosen as ``delta`` is, for the closest mean overlap.

Held-out views: every k-th view of the source order (indices 0, k, 2k, ...) is used by nobody
for training. Each carries ``seen_by``, the robots that saw its part of the scene, so "views
only other robots saw" for robot i are the held-out views whose ``seen_by`` excludes i. With
sectors: the robots whose widened sector contains its azimuth. With a trajectory: the robots
holding the training view nearest to it in pose (distance between camera centres plus the angle
between optical axes times the cameras' median distance to the scene centre), i.e. the robot
that recorded its neighbourhood, or both robots where that view is shared at a border.

Local frames (``T_world_from_local`` maps a robot's local coordinates into the world):
``first_camera`` (the paper's: the robot's first camera is its origin), ``offset`` (the reference
keeps the world frame; every other robot is offset by a fixed rotation and translation),
``world`` (identity: known poses), ``random`` (seeded rotation, translation and optional scale).
Poses become ``transform_c2w(sim3_inverse(T), c2w)``; depths are divided by the scale.
The shared frame g of the swarm is the local frame of the reference robot (the lowest id).

Images only (``images_only``): robot folders get no poses, so each robot's local frame will be
its own SfM's (arbitrary rotation, translation and scale), unknown at split time. ``scene.json``
then has no box (the reference derives it from its SfM), and ``truth.json`` gives, instead of
``T_world_from_local``, the true world cameras of each robot's views (``cameras_world``), to which
the evaluation aligns the robot's SfM cameras (``agent.evaluation.calibrate_frame``).
"""

from agent.data.capture import azimuths_deg, estimate_scene_box, mean_up, scene_center
from agent.data.split.config import DepthPrior, FrameKind, SplitBy, SplitConfig
from agent.data.split.core import RobotSplit, SplitResult, split_dataset, split_views, test_indices
from agent.data.split.frames import offset_transform
from agent.data.split.write import robot_folder, write_split

__all__ = [
    "SplitConfig",
    "FrameKind",
    "DepthPrior",
    "SplitBy",
    "RobotSplit",
    "SplitResult",
    "split_views",
    "split_dataset",
    "test_indices",
    "write_split",
    "robot_folder",
    "estimate_scene_box",
    "scene_center",
    "mean_up",
    "azimuths_deg",
    "offset_transform",
]
