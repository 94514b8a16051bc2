"""How to split a dataset into robots: :class:`SplitConfig` (definitions in :mod:`agent.data.split`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from agent.data.views import DataError

__all__ = ["SplitConfig", "FrameKind", "DepthPrior", "SplitBy"]

FrameKind = Literal["first_camera", "offset", "world", "random"]
DepthPrior = Literal["none", "true", "scaled"]
SplitBy = Literal["sector", "trajectory"]


@dataclass
class SplitConfig:
    """How to split a dataset into robots (see the module docstring for the exact definitions)."""

    robots: int = 2
    ids: list[int] | None = None  # robot ids, default 1..robots; the reference is the lowest
    by: SplitBy = "sector"  # sectors of azimuth (circle or arc), or segments of the capture order
    overlap: float = 0.0  # requested mean fraction of a robot's views shared with a neighbour, [0, 0.4]
    test_every: int = 8  # every k-th view (0, k, 2k, ...) is a test view, seen by no robot; 0 = none
    frame: FrameKind = "first_camera"
    offset_rotation_deg: tuple[float, float, float] = (30.0, 30.0, 30.0)  # about x, then y, then z
    offset_translation: tuple[float, float, float] = (3.0, 3.0, 3.0)
    random_max_angle_deg: float = 180.0
    random_max_translation: float = 3.0  # uniform in the ball of this radius
    random_max_scale: float = 1.0  # > 1: Sim(3), scale log-uniform in [1/x, x]; 1: SE(3)
    depth_prior: DepthPrior = "none"
    depth_scale_range: tuple[float, float] = (0.5, 2.0)  # a_m of the "scaled" prior
    depth_shift_range: tuple[float, float] = (-0.5, 0.5)  # b_m of the "scaled" prior
    up: tuple[float, float, float] | None = None
    center: tuple[float, float, float] | None = None
    sector_start_deg: float = 0.0  # where robot 1's sector begins, when the cameras surround the scene
    images_only: bool = False  # robot folders without poses (robots must run their own SfM)
    calibrated_cameras: bool = False  # images_only: each robot folder also gets its camera's focal length
    # Robot folders get their images at this width (e.g. for their own SfM, which needs more
    # pixels than training); None: the dataset's width as loaded. Test views keep that width.
    robot_image_width: int | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise DataError(f"robots must be >= 1, got {self.robots}")
        if self.ids is not None:
            if len(self.ids) != self.robots or len(set(self.ids)) != len(self.ids) or min(self.ids) < 0:
                raise DataError(f"ids must be {self.robots} distinct non-negative integers, got {self.ids}")
        if not 0.0 <= self.overlap <= 0.4:
            raise DataError(f"overlap must be in [0, 0.4], got {self.overlap}")
        if self.test_every < 0 or self.test_every == 1:
            raise DataError(f"test_every must be 0 (none) or >= 2, got {self.test_every}")
        for name, allowed in (("by", SplitBy), ("frame", FrameKind), ("depth_prior", DepthPrior)):
            if getattr(self, name) not in allowed.__args__:
                raise DataError(f"{name} must be one of {list(allowed.__args__)}, got {getattr(self, name)!r}")
        if self.random_max_scale < 1.0:
            raise DataError(f"random_max_scale must be >= 1, got {self.random_max_scale}")
        if self.calibrated_cameras and not self.images_only:
            raise DataError("calibrated_cameras is for images_only robots (robots with poses have their intrinsics)")
        if self.robot_image_width is not None and self.robot_image_width < 8:
            raise DataError(f"robot_image_width must be >= 8 pixels, got {self.robot_image_width}")
        if self.images_only and self.depth_prior != "none":
            raise DataError("images_only robots have no transforms.json to carry a depth prior; use depth_prior='none'")

    @property
    def robot_ids(self) -> list[int]:
        return sorted(self.ids) if self.ids is not None else list(range(1, self.robots + 1))

