"""Motion control: pure pursuit, VFH obstacle avoidance, stuck detection and recovery, and
the driver that makes every command from them.

All return :class:`Twist` (v [m/s], ω [rad/s]) and do no I/O:

    driver = Driver(Vfh())
    drive = driver.follow(PurePursuit(params), pose, path_xy,
                          Obstacles(scan_points_robot_xy, other_robots_robot_xy))
    if stuck.update(stamp_s, pose): recovery.start(stamp_s, scan_points_robot_xy)
"""

from server.control.driver import Drive, Driver, Obstacles, limit
from server.control.geometry import STOP, Twist, clip, world_to_robot
from server.control.memory import ObstacleMemory
from server.control.pure_pursuit import PurePursuit, PursuitParams, PursuitStep, closest_point
from server.control.stuck import (
    Recovery,
    RecoveryParams,
    StampOrderError,
    StuckDetector,
)
from server.control.vfh import Vfh, VfhParams, VfhResult

__all__ = [
    "STOP",
    "Drive",
    "Driver",
    "ObstacleMemory",
    "Obstacles",
    "PurePursuit",
    "PursuitParams",
    "PursuitStep",
    "Recovery",
    "RecoveryParams",
    "StampOrderError",
    "StuckDetector",
    "Twist",
    "Vfh",
    "VfhParams",
    "VfhResult",
    "clip",
    "closest_point",
    "limit",
    "world_to_robot",
]
