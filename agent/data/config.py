"""``[data]``: how a robot's own recording is read (the formats that need settings)."""

from __future__ import annotations

from dataclasses import dataclass, field

from agent.data.ros.config import RosBagConfig
from agent.data.stream import StreamConfig

__all__ = ["DataConfig"]


@dataclass
class DataConfig:
    ros: RosBagConfig = field(default_factory=RosBagConfig)  # [data.ros]: ROS 2 bags
    stream: StreamConfig = field(default_factory=StreamConfig)  # [data.stream]: views that arrive while training
