"""ROS messages of a bag as the log records of ``server.offline.logs.records``: laser scans
(single- and multi-echo) and poses (odometry, transforms).

Ranges outside the scan's ``[range_min, range_max]`` and non-finite ones (REP 117: ``+inf`` no
return, ``-inf`` too close, NaN invalid) are no return (``inf``). A multi-echo beam gives its
first echo (the nearest surface: what a single-echo scanner reports) or, asked for, its last
(what lies behind glass, rain or foliage); a beam without echoes is no return.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np

from server.offline.logs.records import F64, LaserRecord

LASER_SCAN = "sensor_msgs/msg/LaserScan"
MULTI_ECHO = "sensor_msgs/msg/MultiEchoLaserScan"
SCAN_TYPES = (LASER_SCAN, MULTI_ECHO)
ODOMETRY = "nav_msgs/msg/Odometry"
#: ``tf/tfMessage`` is what ROS 1 recorded on /tf before tf2
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
Echo = Literal["first", "last"]


def yaw_of(q: Any) -> float:
    """Rotation about z [rad] of a quaternion message (x, y, z, w)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def frame(name: str) -> str:
    return name.lstrip("/")   # ROS 1 frames may carry a leading slash


def stamp(header: Any, receive_ns: int) -> tuple[str, float]:
    """The header stamp as text (``sec.nanosec``) and seconds; an unset (zero) stamp is
    replaced by the time the bag received the message."""
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    if sec == 0 and nsec == 0:
        sec, nsec = divmod(int(receive_ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}", sec + nsec * 1e-9


def pose_of(p: Any) -> F64:
    """(x, y, θ) of a ``geometry_msgs/Pose``."""
    return np.array([float(p.position.x), float(p.position.y), yaw_of(p.orientation)])


def transform_of(t: Any) -> F64:
    """(x, y, θ) of a ``geometry_msgs/Transform``."""
    return np.array([float(t.translation.x), float(t.translation.y), yaw_of(t.rotation)])


def echo_ranges(echoes: Any, echo: Echo) -> F64:
    """One range per beam of a ``MultiEchoLaserScan``'s ``ranges`` (``LaserEcho[]``)."""
    pick = 0 if echo == "first" else -1
    return np.array([float(e.echoes[pick]) if len(e.echoes) else math.inf for e in echoes],
                    dtype=np.float32)


def laser_record(msg: Any, msgtype: str, receive_ns: int, number: int,
                 echo: Echo = "first") -> LaserRecord:
    """A ``LaserScan`` or ``MultiEchoLaserScan`` as a laser record without a pose."""
    text, t = stamp(msg.header, receive_ns)
    raw = echo_ranges(msg.ranges, echo) if msgtype == MULTI_ECHO else np.asarray(msg.ranges)
    # float32 ranges read as the decimal they print as (8.13, not 8.1300001144): a log
    # converted to a bag gives back its own readings
    ranges = raw.astype(str).astype(np.float64) if raw.dtype == np.float32 else \
        raw.astype(np.float64)
    lo, hi = float(msg.range_min), float(msg.range_max)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(ranges) | (ranges < lo) | ((ranges > hi) if math.isfinite(hi) and
                                                      hi > 0 else False)
    ranges = np.where(bad, np.inf, ranges).astype(np.float64)
    angles = float(msg.angle_min) + float(msg.angle_increment) * np.arange(len(ranges),
                                                                           dtype=np.float64)
    max_r = hi if math.isfinite(hi) and hi > 0 else None
    kind = "MultiEchoLaserScan" if msgtype == MULTI_ECHO else "LaserScan"
    return LaserRecord(kind, text, t, ranges, angles, max_r, None, None, number)
