"""Reader for ROS bags (ROS 1 ``.bag`` files, ROS 2 bag folders in SQLite or MCAP storage): the
laser scans of one ``sensor_msgs/LaserScan`` topic with the odometry pose of the laser at each.

Odometry comes from a ``nav_msgs/Odometry`` topic, else from ``/tf``: the transform whose child
is the frame the scan hangs from (through ``/tf_static``). Where the scan's frame is mounted on
that frame by static transforms, the mount is composed in, so each scan gets the pose of the
laser itself. Stamps are the messages' header stamps; ranges outside the scan's
``[range_min, range_max]`` and non-finite ones (REP 117: ``+inf`` no return, ``-inf`` too close,
NaN invalid) are no return (``inf``).
"""

from __future__ import annotations

import logging
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas.se2 import wrap_angle
from server.logs.odometry import interpolate_pose
from server.logs.records import (
    F64,
    CarmenError,
    CarmenLog,
    LaserRecord,
    OdometryRecord,
    ReadStats,
)

log = logging.getLogger(__name__)

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"


class BagError(CarmenError):
    """A bag that cannot be used: not a bag, no laser scan topic, no odometry, unreadable."""


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a ROS 2 bag folder, or a file inside a ROS 2 bag folder."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.suffix == ".bag":
        return True
    return path.suffix in (".mcap", ".db3") and (path.parent / "metadata.yaml").is_file()


def yaw_of(q: Any) -> float:
    """Rotation about z [rad] of a quaternion message (x, y, z, w)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def compose(a: F64, b: F64) -> F64:
    """SE(2) a ⊕ b for (x, y, θ) arrays."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     wrap_angle(a[2] + b[2])])


def _stamp(header: Any) -> tuple[str, float, int]:
    sec, nsec = int(header.stamp.sec), int(header.stamp.nanosec)
    return f"{sec}.{nsec:09d}", sec + nsec * 1e-9, sec * 1_000_000_000 + nsec


def _pose2(p: Any) -> F64:
    return np.array([float(p.position.x), float(p.position.y), yaw_of(p.orientation)])


def _tf2(t: Any) -> F64:
    return np.array([float(t.translation.x), float(t.translation.y), yaw_of(t.rotation)])


def _frame(name: str) -> str:
    return name.lstrip("/")   # ROS 1 frames may carry a leading slash


@dataclass
class _Collected:
    scans: list[tuple[Any, int]] = field(default_factory=list)        # (message, number)
    odometry: list[tuple[float, str, str, F64]] = field(default_factory=list)
    odom_child: str | None = None
    #: child frame -> (parent frame, pose of the child in the parent)
    static: dict[str, tuple[str, F64]] = field(default_factory=dict)
    dynamic: dict[str, list[tuple[float, str, str, F64]]] = field(default_factory=dict)


def _choose(topics: dict[str, tuple[str, int]], msgtype: str, wanted: str | None,
            what: str) -> str | None:
    found = {t: n for t, (ty, n) in topics.items() if ty == msgtype}
    if wanted is not None:
        if wanted not in topics:
            raise BagError(f"no topic {wanted!r} in the bag (topics: {sorted(topics)})")
        if topics[wanted][0] != msgtype:
            raise BagError(f"topic {wanted!r} carries {topics[wanted][0]}, not {msgtype}")
        return wanted
    if not found:
        return None
    best = max(found, key=lambda t: found[t])
    if len(found) > 1:
        log.warning("several %s topics %s: using %s (the most messages)", what, sorted(found),
                    best)
    return best


def _open(path: Path) -> Any:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if path.suffix in (".mcap", ".db3") and not path.is_dir():
        path = path.parent
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))


def _collect(reader: Any, scan_topic: str, odom_topic: str | None,
             stats: ReadStats) -> _Collected:
    from rosbags.serde import SerdeError

    got = _Collected()
    wanted = {scan_topic} | ({odom_topic} if odom_topic else set()) | {"/tf", "/tf_static"}
    conns = [c for c in reader.connections if c.topic in wanted
             and c.msgtype in (LASER_SCAN, ODOMETRY, TF)]
    number = 0
    for conn, _, raw in reader.messages(connections=conns):
        number += 1
        stats.lines += 1
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except (SerdeError, ValueError, IndexError, struct.error) as e:   # skipped, counted
            stats.skip("corrupt", number, f"{conn.topic}: {type(e).__name__}: {e}")
            continue
        stats.by_kind[conn.topic] += 1
        if conn.topic == scan_topic:
            got.scans.append((msg, number))
        elif conn.topic == odom_topic:
            text, t, _ = _stamp(msg.header)
            got.odom_child = _frame(msg.child_frame_id)
            got.odometry.append((t, text, _frame(msg.header.frame_id), _pose2(msg.pose.pose)))
        elif conn.msgtype == TF:
            for tr in msg.transforms:
                child, parent = _frame(tr.child_frame_id), _frame(tr.header.frame_id)
                if conn.topic == "/tf_static":
                    got.static[child] = (parent, _tf2(tr.transform))
                else:
                    text, t, _ = _stamp(tr.header)
                    got.dynamic.setdefault(child, []).append((t, text, parent,
                                                              _tf2(tr.transform)))
    return got


def _mount(static: dict[str, tuple[str, F64]], frame: str, base: str | None
           ) -> tuple[str, F64]:
    """Walk the static transforms up from ``frame`` (to ``base``, or to the first frame with no
    static parent): that frame and the pose of ``frame`` in it."""
    pose = np.zeros(3)
    seen = {frame}
    while frame != base and frame in static:
        parent, T = static[frame]
        pose = compose(T, pose)
        frame = parent
        if frame in seen:
            raise BagError(f"/tf_static has a loop through {frame!r}")
        seen.add(frame)
    return frame, pose


def _laser_record(msg: Any, number: int) -> LaserRecord:
    text, t, _ = _stamp(msg.header)
    raw = np.asarray(msg.ranges)
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
    return LaserRecord("LaserScan", text, t, ranges, angles, max_r, None, None, number)


def read_bag(path: str | Path, scan_topic: str | None = None,
             odom_topic: str | None = None) -> tuple[CarmenLog, str]:
    """The scans of a bag with the laser's odometry pose in each (``laser_pose``) and the
    odometry it came from; returns them as a ``CarmenLog`` and a line saying where the odometry
    came from. Raises ``BagError`` naming what is missing."""
    from rosbags.highlevel import AnyReaderError

    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such file or folder")
    stats = ReadStats()
    try:
        with _open(p) as reader:
            topics = {t: (i.msgtype or "", int(i.msgcount)) for t, i in reader.topics.items()}
            scan = _choose(topics, LASER_SCAN, scan_topic, "LaserScan")
            if scan is None:
                raise BagError(f"{p}: no sensor_msgs/LaserScan topic in the bag (topics: "
                               f"{ {t: ty for t, (ty, _) in topics.items()} })")
            odom = _choose(topics, ODOMETRY, odom_topic, "Odometry")
            got = _collect(reader, scan, odom, stats)
    except AnyReaderError as e:
        raise BagError(f"{p}: not a readable ROS bag ({e})") from None
    if not got.scans:
        raise BagError(f"{p}: the topic {scan} holds no readable LaserScan message")
    lasers = [_laser_record(m, n) for m, n in got.scans]
    scan_frame = _frame(got.scans[0][0].header.frame_id)
    base, T_base_laser = _mount(got.static, scan_frame, got.odom_child)
    if got.odometry:
        source = f"{odom} ({got.odom_child} in {got.odometry[0][2]})"
        samples = got.odometry
        if got.odom_child and base != got.odom_child:
            log.warning("%s: the scans' frame %r is not tied to the odometry's %r by "
                        "/tf_static: taking the laser at the robot's origin", p, scan_frame,
                        got.odom_child)
            T_base_laser = np.zeros(3)
    elif base in got.dynamic:
        samples = got.dynamic[base]
        source = f"/tf ({base} in {samples[0][2]})"
    else:
        raise BagError(f"{p}: no odometry: no nav_msgs/Odometry topic, and /tf has no "
                       f"transform to the scans' frame {scan_frame!r} (or a frame it is "
                       f"mounted on through /tf_static)")
    odometry = [OdometryRecord(text, t, pose, 0) for t, text, _, pose in samples]
    stamps = np.array([o.stamp_s for o in odometry])
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], np.array([o.pose for o in odometry])[order]
    placed = []
    for rec in lasers:
        robot = interpolate_pose(stamps, poses, rec.stamp_s)
        placed.append(LaserRecord(rec.kind, rec.stamp_text, rec.stamp_s, rec.ranges_m,
                                  rec.angles_rad, rec.max_range_m, compose(robot, T_base_laser),
                                  robot, rec.line_no))
    log.info("%s: %d scans on %s, odometry from %s", p, len(placed), scan, source)
    return CarmenLog(placed, odometry, {}, stats), f"{scan}; odometry {source}"

