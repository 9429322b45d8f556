"""Per-robot graph SLAM: scan-matching front-end, GTSAM/ISAM2 back-end, loop closure, maps.

The entry point is ``RobotSlam``; ``SlamConfig`` holds its settings."""

from server.slam.config import SlamConfig
from server.slam.errors import SlamInputError
from server.slam.robot import RobotSlam

__all__ = ["RobotSlam", "SlamConfig", "SlamInputError"]
