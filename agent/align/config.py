"""Settings of the coarse alignment: the summary a robot publishes and the pairwise estimate."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from agent.config_io import check

__all__ = ["AlignConfig"]


@dataclass(frozen=True)
class AlignConfig:
    """Settings of the summary and of the pairwise estimate; defaults run in seconds on 2 cores."""

    # --- summary (per robot) ---
    num_keyframes: int = 48  # K keyframes spread over the robot's views (all views if fewer): more
    # viewpoints match more of a neighbour's views; the byte budget still caps the payload
    max_bytes: int = 256_000  # cap on the payload: P <= max_bytes // 144
    # a robot that keeps mapping summarises this many of its keyframes, spread over them: its
    # keyframes and their triangulation partners (num_keyframes x (1 + neighbours_per_keyframe))
    summary_pool: int = 240
    sift_features: int = 2000  # SIFT detections per image
    sift_contrast: float = 0.02  # OpenCV contrastThreshold (lower = more features on flat CGI)
    neighbours_per_keyframe: int = 4  # own views matched to a keyframe to triangulate its features
    neighbour_angle_deg: float = 15.0  # preferred angle between keyframe and neighbour viewing directions
    neighbour_max_angle_deg: float = 50.0
    own_ratio: float = 0.8  # Lowe ratio for matches within the robot
    max_reproj_px: float = 2.0  # triangulated points must reproject this well in every view used
    min_parallax_deg: float = 2.0  # and be seen under at least this angle
    depth_search_px: int = 1  # "depth" source: look this far around a keypoint for a depth value
    depth_dense_fraction: float = 0.05  # "auto" uses depth only if this fraction of pixels has it
    descriptor_scale: float = 512.0  # RootSIFT -> uint8 quantisation factor
    # --- matching and RANSAC (pairwise) ---
    # Sim(3) estimates, or SE(3) for robots that share a metric scale; None: as the robots' poses
    # are learnt (training.train.pose.mode, see for_pose_mode), which a robot must agree with.
    with_scale: bool | None = None
    match_ratio: float = 0.85  # Lowe ratio against the best match of a *different* 3-D point
    dup_radius: float = 0.02  # same physical point if closer than this fraction of the scene radius
    ransac_iters: int = 3000
    inlier_threshold: float = 0.04  # fraction of the scene radius of the summary we map into
    min_sample_spread: float = 0.05  # minimal samples must span a triangle this wide (x radius)
    refine_iters: int = 5
    # Reprojection refinement (when both summaries carry keypoints and keyframe cameras): the 3-D
    # points' error lies mostly along their viewing rays (depth from a narrow baseline), which a
    # 3-D/3-D fit weighs as much as the lateral error. Measuring each match in pixels of the other
    # robot's keyframe weighs it as the cameras saw it, as ORB-SLAM's Sim(3) loop closure does.
    reproj_refine: bool = True
    reproj_candidates: float = 2.0  # matches within this x the 3-D inlier threshold take part
    reproj_scale_px: float = 1.0  # Cauchy loss scale, in pixels of the keyframes
    reproj_iters: int = 30  # Levenberg-Marquardt iterations
    reproj_max_change_deg: float = 5.0  # a refinement that turns the 3-D estimate more is refused
    seed: int = 0
    # --- decision ---
    min_inliers: int = 12
    min_inlier_ratio: float = 0.05
    null_factor: float = 2.0  # inliers must be >= this x the best count on shuffled matches
    min_spread: float = 0.1  # inliers' 2nd principal std must be >= this x the scene radius
    scale_range: tuple[float, float] = (1e-3, 1e3)

    def __post_init__(self) -> None:
        check(self, num_keyframes=">= 1", summary_pool=">= 1")

    @property
    def sim3(self) -> bool:
        """Whether estimates carry a scale (unset counts as Sim(3), the general case)."""
        return self.with_scale is not False

    def for_pose_mode(self, mode: str) -> "AlignConfig":
        """These settings for robots whose relative poses are ``mode`` (fixed | se3 | sim3): a
        Sim(3) start for an SE(3) pose would carry a scale the pose cannot hold, and a wrong map."""
        want = mode == "sim3"
        if self.with_scale is not None and self.with_scale != want:
            raise ValueError(f"align.with_scale = {str(self.with_scale).lower()} contradicts training.train.pose.mode = "
                             f"{mode!r} (Sim(3) estimates are for sim3 poses); leave align.with_scale unset")
        return dataclasses.replace(self, with_scale=want)
