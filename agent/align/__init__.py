"""Coarse initial relative pose between robots, without sharing images.

Joint NeRF + pose optimisation only converges from within roughly 45 deg / 1 m of the truth.
Robots with their own SfM start from arbitrary frames and scales, so this module gives the
optimisation a starting point from cheap geometry:

1. :func:`summarise`: each robot picks K keyframes spread over its views and keeps the SIFT
   features (RootSIFT, uint8) that it can place in 3-D in *its own* local frame: from a metric
   depth prior, or by triangulating against its other views with its known local poses. The
   payload (descriptors [P, 128] uint8, points [P, 3] float32, keyframe_index [P] int32,
   keypoints [P, 2] float32, keyframe_cameras [K, 16] float32) is a few hundred KB, far less
   than the images, and reveals no pixels.
2. :func:`estimate_relative`: a neighbour matches the descriptors (ratio test + mutual check,
   both aware that one 3-D point appears in several keyframes), fits a Sim(3) (or SE(3)) to the
   3-D/3-D matches by RANSAC over minimal Umeyama samples, refits on the inliers and decides.
   The decision compares the inlier count with what the same RANSAC finds on *shuffled*
   matches, so "no overlap" yields ``success=False`` with a reason instead of a wrong pose.
   The accepted estimate is then refined on the symmetric reprojection error of the matches
   (:func:`refine_by_reprojection`), which weighs each point as the keyframes saw it.
3. :func:`compose_along_graph`: pairwise estimates are chained from the reference robot along
   a best-inlier spanning tree, so robots that do not neighbour the reference get a start too.

Trainer usage (robot i, reference r)::

    s_i = summarise(views_i)                       # once, published to the neighbours
    res = estimate_relative(s_j, s_i)              # on neighbour j: T_j_from_i (or a reason)
    T = compose_along_graph(r, {(j, i): res, ...}).get(i)   # T_r_from_i = initial T_i, or None
    T, res = initial_pose(views_i, s_r)            # the one-hop case, identity if nothing found

Everything is numpy/OpenCV on the CPU and deterministic for ``AlignConfig.seed``.

Modules: ``config`` (:class:`AlignConfig`), ``payload`` (:class:`Summary`, :class:`AlignmentResult`),
``features`` and ``placement`` (a robot's SIFT features and their 3-D points), ``keypoints``
(rays, projection and triangulation in OpenCV keypoint coordinates), ``summary``, ``matching``
(descriptor matches, RANSAC), ``refine`` (reprojection refinement), ``estimate`` (the pairwise
decision) and ``graph`` (composition along the robots' graph).
"""

from agent.align.config import AlignConfig
from agent.align.estimate import estimate_relative, initial_pose
from agent.align.graph import compose_along_graph
from agent.align.keypoints import triangulate_rays
from agent.align.matching import match_summaries, ransac_sim3
from agent.align.payload import SUMMARY_VERSION, AlignmentResult, Summary
from agent.align.refine import refine_by_reprojection
from agent.align.summary import summarise

__all__ = [
    "AlignConfig",
    "Summary",
    "AlignmentResult",
    "SUMMARY_VERSION",
    "summarise",
    "estimate_relative",
    "compose_along_graph",
    "initial_pose",
    "match_summaries",
    "ransac_sim3",
    "refine_by_reprojection",
    "triangulate_rays",
]
