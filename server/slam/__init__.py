"""Per-robot graph SLAM: scan-matching front-end, GTSAM/ISAM2 back-end, loop closure, maps.

``RobotSlam`` (``robot``) runs the method one scan at a time; ``SlamConfig`` holds its settings
(one default for every sensor and building). Modules, one stage each: ``scan`` (ranges → points
and normals), ``icp`` and ``correlative`` (matchers), ``frontend`` (which match to trust),
``measurements`` (a match between two keyframes as a factor), ``keyframes`` (local maps),
``scan_poses`` (the robot's pose and every scan's, relative to keyframes), ``backend``
(trajectories and the ISAM2 graph), ``loop_closure`` and ``closures`` (finding loops, adding
them), ``grid``/``mapping``/``export`` (occupancy grid, point cloud, nav2 and PLY files).

What a kind of sensor needs besides is its ``SensorModel`` (``sensor``: the interface and the
360° LIDAR's; ``view``: what it may read of the robot): ``narrow`` for a depth camera, with
``smoothing`` (its poses averaged), ``sweep`` (whole scans standing still) and ``heading`` /
``heading_ties`` (square walls).
"""

from server.slam.config import SlamConfig
from server.slam.errors import SlamInputError
from server.slam.robot import RobotSlam

__all__ = ["RobotSlam", "SlamConfig", "SlamInputError"]
