"""What crosses the network for the coarse alignment (:class:`Summary`) and what it yields."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from protocol.messages import KEYFRAME_CAMERA_DIM

__all__ = ["Summary", "AlignmentResult", "SUMMARY_VERSION", "DESC_DIM", "BYTES_PER_POINT"]

SUMMARY_VERSION = 2  # 2: keypoints and keyframe cameras (for the reprojection refinement)
DESC_DIM = 128
BYTES_PER_POINT = DESC_DIM + 3 * 4 + 4 + 2 * 4  # uint8 descriptor + float32 xyz + int32 keyframe + float32 uv


@dataclass
class Summary:
    """What a robot publishes about its keyframes: descriptors and the 3-D points they see."""

    descriptors: np.ndarray  # [P, 128] uint8: RootSIFT * descriptor_scale
    points: np.ndarray  # [P, 3] float32, robot's local frame
    keyframe_index: np.ndarray  # [P] int32, which keyframe (0..K-1) saw the feature
    descriptor_scale: float = 512.0
    keypoints: np.ndarray | None = None  # [P, 2] float32: OpenCV pixel position in its keyframe
    keyframe_cameras: np.ndarray | None = None  # [K, 16] float32: c2w rows 0-2 (OpenGL) + fx, fy, cx, cy
    meta: dict = field(default_factory=dict)  # local statistics only; not part of the payload

    def __post_init__(self) -> None:
        p = self.points.shape[0]
        if self.descriptors.dtype != np.uint8 or self.descriptors.shape != (p, DESC_DIM):
            raise ValueError(f"descriptors must be uint8 [{p}, {DESC_DIM}], got {self.descriptors.dtype} "
                             f"{self.descriptors.shape}")
        if self.points.dtype != np.float32 or self.points.shape != (p, 3) or not np.isfinite(self.points).all():
            raise ValueError(f"points must be finite float32 [P, 3], got {self.points.dtype} {self.points.shape}")
        if self.keyframe_index.dtype != np.int32 or self.keyframe_index.shape != (p,):
            raise ValueError(f"keyframe_index must be int32 [{p}], got {self.keyframe_index.dtype} "
                             f"{self.keyframe_index.shape}")
        if not (self.descriptor_scale > 0 and math.isfinite(self.descriptor_scale)):
            raise ValueError(f"descriptor_scale must be positive, got {self.descriptor_scale}")
        if (self.keypoints is None) != (self.keyframe_cameras is None):
            raise ValueError("keypoints and keyframe_cameras come together (or neither)")
        if self.keypoints is not None:
            kp, cams = self.keypoints, self.keyframe_cameras
            if kp.dtype != np.float32 or kp.shape != (p, 2) or not np.isfinite(kp).all():
                raise ValueError(f"keypoints must be finite float32 [{p}, 2], got {kp.dtype} {kp.shape}")
            if cams.dtype != np.float32 or cams.ndim != 2 or cams.shape[1] != KEYFRAME_CAMERA_DIM or not np.isfinite(cams).all():
                raise ValueError(f"keyframe_cameras must be finite float32 [K, {KEYFRAME_CAMERA_DIM}], got {cams.dtype} {cams.shape}")
            if p and (self.keyframe_index.min() < 0 or self.keyframe_index.max() >= len(cams)):
                raise ValueError(f"keyframe_index outside the {len(cams)} keyframe cameras")
            if len(cams) and not (cams[:, 12:14] > 0).all():
                raise ValueError("keyframe focal lengths must be positive")

    @property
    def has_cameras(self) -> bool:
        return self.keypoints is not None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays that cross the network (before any compression)."""
        extra = self.keypoints.nbytes + self.keyframe_cameras.nbytes if self.has_cameras else 0
        return int(self.descriptors.nbytes + self.points.nbytes + self.keyframe_index.nbytes + extra)

    def radius(self) -> float:
        """Robust scene radius: median distance of the points to their per-axis median."""
        if len(self) == 0:
            return 0.0
        return float(np.median(np.linalg.norm(self.points - np.median(self.points, 0), axis=1)))

    def to_arrays(self) -> dict:
        """Plain payload for the protocol layer (numpy arrays and scalars only)."""
        out = {
            "version": SUMMARY_VERSION,
            "descriptor_scale": float(self.descriptor_scale),
            "descriptors": self.descriptors,
            "points": self.points,
            "keyframe_index": self.keyframe_index,
        }
        if self.has_cameras:
            out.update(keypoints=self.keypoints, keyframe_cameras=self.keyframe_cameras)
        return out

    @classmethod
    def from_arrays(cls, payload: Mapping) -> "Summary":
        """Inverse of :meth:`to_arrays`; validates everything (the payload came from another robot)."""
        if payload.get("version") not in (1, SUMMARY_VERSION):
            raise ValueError(f"summary version {payload.get('version')!r}, expected 1 or {SUMMARY_VERSION}")
        kp, cams = payload.get("keypoints"), payload.get("keyframe_cameras")
        return cls(
            descriptors=np.asarray(payload["descriptors"]),
            points=np.asarray(payload["points"]),
            keyframe_index=np.asarray(payload["keyframe_index"]),
            descriptor_scale=float(payload["descriptor_scale"]),
            keypoints=None if kp is None else np.asarray(kp),
            keyframe_cameras=None if cams is None else np.asarray(cams),
        )


@dataclass
class AlignmentResult:
    """Outcome of one pairwise estimate. ``T_a_from_b`` maps b's local points into a's frame."""

    T_a_from_b: np.ndarray | None  # [4, 4] float64 [sR | t], None when not successful
    inliers: int
    matches: int
    rmse: float  # of the inliers, in a's units (nan without a model)
    success: bool
    reason: str
    null_inliers: int = 0  # best inlier count of the same RANSAC on shuffled matches
    scale: float = float("nan")
    # 1-sigma of the rotation, from the reprojection refinement's information matrix (nan without
    # it): how far the joint optimisation may need to move the estimate (PoseConfig.travel_sigmas).
    rotation_sigma_deg: float = float("nan")
