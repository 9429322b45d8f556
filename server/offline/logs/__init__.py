"""Reading robot logs (CARMEN) into laser scans with odometry."""

from server.offline.logs.carmen import LaserLines, guess_beam_angles, parse_line, read_log
from server.offline.logs.odometry import (
    OdometryScan,
    attach_odometry,
    choose_odometry_source,
    laser_poses_are_stale,
    select_stream,
)
from server.offline.logs.records import (
    CarmenError,
    CarmenLog,
    LaserRecord,
    LineError,
    OdometryRecord,
    ReadStats,
)

__all__ = ["CarmenError", "CarmenLog", "LaserLines", "LaserRecord", "LineError", "OdometryRecord",
           "OdometryScan", "ReadStats", "attach_odometry", "choose_odometry_source",
           "guess_beam_angles",
           "laser_poses_are_stale", "parse_line", "read_log", "select_stream"]
