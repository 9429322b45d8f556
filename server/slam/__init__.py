"""Per-robot graph SLAM: scan-matching front-end, GTSAM/ISAM2 back-end, loop closure, maps.

``RobotSlam`` runs the method one scan at a time; ``SlamConfig`` holds its settings (one
default for every sensor and building). Modules, one stage each: ``scan`` (ranges → points and
normals), ``icp`` and ``correlative`` (matchers), ``frontend`` (which match to trust),
``keyframes`` (local maps), ``backend`` (trajectories and the ISAM2 graph), ``loop_closure``,
``grid``/``mapping``/``export`` (occupancy grid, point cloud, nav2 and PLY files).
"""

from server.slam.config import SlamConfig
from server.slam.errors import SlamInputError
from server.slam.robot import RobotSlam

__all__ = ["RobotSlam", "SlamConfig", "SlamInputError"]
