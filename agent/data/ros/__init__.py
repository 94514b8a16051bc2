"""ROS 2 recordings as a robot's data: rosbag2 (MCAP, sqlite3) read with ``rosbags``, no ROS needed.

:mod:`bag` turns a bag into the robot's keyframes; :mod:`tf` is the tf tree; :mod:`decode` the
camera messages; :mod:`keyframes` which frames are kept; :mod:`record` writes bags from views
(tests, benchmarks, scenarios); :mod:`config` is ``[data.ros]``.
"""

from agent.data.ros.bag import BagReport, extract_keyframes, is_bag, load_bag
from agent.data.ros.config import KeyframeConfig, RosBagConfig

__all__ = ["BagReport", "extract_keyframes", "is_bag", "load_bag", "KeyframeConfig", "RosBagConfig"]
