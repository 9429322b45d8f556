"""Motion control: pure pursuit, VFH obstacle avoidance, stuck detection and recovery.

All return :class:`Twist` (v [m/s], ω [rad/s]) and do no I/O:

    pp = PurePursuit(PursuitParams(lookahead_m=1.0, v_mps=0.3, omega_max_rps=1.5))
    step = pp.step(pose, path_xy)                      # twist, reached, heading error
    twist = Vfh().adjust(step.twist, step.heading_error_rad, scan_points_robot_xy)
    if stuck.update(stamp_s, pose): recovery.start(stamp_s, scan_points_robot_xy)
"""

from server.control.geometry import STOP, Twist, clip, world_to_robot
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
    "world_to_robot",
]
