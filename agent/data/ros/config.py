"""``[data.ros]``: how a robot's ROS 2 bag becomes its views (topics, frames, tf tolerance, keyframes)."""

from __future__ import annotations

from dataclasses import dataclass, field

from agent.config_io import InvalidValue, check

__all__ = ["RosBagConfig", "KeyframeConfig"]


@dataclass
class KeyframeConfig:
    """Which of a camera's 10-30 frames a second are kept: motion since the last keyframe, then sharpness.

    A frame is a candidate once the camera has moved ``min_translation`` or turned
    ``min_rotation_deg`` since the last candidate; of it and the ``sharpness_window - 1`` frames
    after it, the sharpest (variance of the Laplacian) is kept. A bag with more candidates than
    ``max_keyframes`` gets both thresholds raised together until it fits, so the budget spreads
    over the whole trajectory rather than ending it early.
    """

    min_translation: float = 0.0  # in the bag's units (metres); 0: 2% of the trajectory's extent
    min_rotation_deg: float = 5.0
    sharpness_window: int = 5  # frames compared for sharpness after each trigger (1 = no choice)
    max_keyframes: int = 300  # 0 = no budget

    def __post_init__(self) -> None:
        check(self, min_translation=">= 0", min_rotation_deg=">= 0", sharpness_window=">= 1", max_keyframes=">= 0")


@dataclass
class RosBagConfig:
    """Streams of a rosbag2 recording (MCAP or sqlite3) and how they are read."""

    image_topic: str | None = None  # None: the bag's one camera (sensor_msgs Image or CompressedImage)
    camera_info_topic: str | None = None  # None: the CameraInfo beside the image topic
    fixed_frame: str | None = None  # where poses are expressed; None: the root of the tf tree (odom, map)
    camera_frame: str | None = None  # None: the images' header.frame_id (ROS optical: x right, y down, z forward)
    # Transforms are interpolated (slerp) between two samples at most this far apart, never
    # extrapolated: an image outside, or in a wider gap, has no pose and is skipped.
    tf_max_gap_s: float = 0.2
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)

    def __post_init__(self) -> None:
        check(self, tf_max_gap_s="> 0")
        for name in ("image_topic", "camera_info_topic"):
            value = getattr(self, name)
            if value is not None and not value.startswith("/"):
                raise InvalidValue(name, f"must be an absolute topic name (/camera/image_raw), got {value!r}")
