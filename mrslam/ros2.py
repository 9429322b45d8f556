"""``mrslam export ... --ros2 OUT``: a recording (``run.mcap``) or a CARMEN log as a ROS 2 bag
(rosbag2, MCAP storage, Jazzy message definitions) that ``ros2 bag play`` and RViz take.

From a recording, per robot ``/<id>/scan`` (``sensor_msgs/msg/LaserScan``, frame
``<id>/base_link``, no return ``+inf`` as REP 117 says), ``/tf`` with ``<id>/odom →
<id>/base_link`` at every scan (wheel odometry) and ``<team>/map → <id>/odom`` at every
estimate the server published (so the scan sits where the server placed the robot),
``/<id>/path`` (``nav_msgs/msg/Path``: the robot's estimates in its team's map, every 5 s) and
per team ``/map/<team>`` (``nav_msgs/msg/OccupancyGrid``). From a CARMEN log: ``/scan``,
``/odom`` (``nav_msgs/msg/Odometry`` of ``base_link`` at each scan) and ``/tf_static`` with the
laser's mount, which ``mrslam slam-log`` reads back to the same laser poses.

Ids become ROS names: every character other than a letter, digit or ``_`` turns into ``_``.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

PATH_PERIOD_NS = 5_000_000_000
PATH_STEP_M, PATH_STEP_RAD = 0.05, 0.05


class ExportError(ValueError):
    """Nothing to export, or an output that cannot be written."""

    user_error = True


def ros_name(text: str) -> str:
    """An id as a ROS name token (``team-r1`` -> ``team_r1``)."""
    name = re.sub(r"[^A-Za-z0-9_]", "_", text)
    return name if name and not name[0].isdigit() else f"_{name}"


class BagWriter:
    """A rosbag2 writer (MCAP storage) that opens a connection per topic on first use."""

    def __init__(self, out: Path) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        out = Path(out)
        if out.exists():
            raise ExportError(f"{out}: exists already (rosbag2 writes a new folder)")
        self.ts = get_typestore(Stores.ROS2_JAZZY)
        self.writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
        self.conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self.t = self.ts.types

    def __enter__(self) -> BagWriter:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        self.writer.write(self.conns[topic], stamp_ns,
                          self.ts.serialize_cdr(msg, msgtype))
        self.counts[topic] = self.counts.get(topic, 0) + 1

    # message builders --------------------------------------------------------------------
    def header(self, stamp_ns: int, frame: str) -> Any:
        t = self.t
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                                   nanosec=stamp_ns % 1_000_000_000),
            frame_id=frame)

    def pose(self, x: float, y: float, yaw: float) -> Any:
        t = self.t
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
            orientation=self.quat(yaw))

    def quat(self, yaw: float) -> Any:
        return self.t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                      w=math.cos(yaw / 2))

    def transform(self, stamp_ns: int, parent: str, child: str, x: float, y: float,
                  yaw: float) -> Any:
        t = self.t
        return t["geometry_msgs/msg/TransformStamped"](
            header=self.header(stamp_ns, parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=0.0),
                rotation=self.quat(yaw)))

    def tf(self, stamp_ns: int, transforms: list[Any], static: bool = False) -> None:
        self.write("/tf_static" if static else "/tf", "tf2_msgs/msg/TFMessage", stamp_ns,
                   self.t["tf2_msgs/msg/TFMessage"](transforms=transforms))

    def scan(self, topic: str, stamp_ns: int, frame: str, angle_min: float, increment: float,
             range_min: float, range_max: float, ranges_m: np.ndarray) -> None:
        n = len(ranges_m)
        self.write(topic, "sensor_msgs/msg/LaserScan", stamp_ns,
                   self.t["sensor_msgs/msg/LaserScan"](
                       header=self.header(stamp_ns, frame), angle_min=float(angle_min),
                       angle_max=float(angle_min + increment * (n - 1)),
                       angle_increment=float(increment), time_increment=0.0, scan_time=0.0,
                       range_min=float(range_min), range_max=float(range_max),
                       ranges=np.asarray(ranges_m, dtype=np.float32),
                       intensities=np.zeros(0, dtype=np.float32)))


# a recording ------------------------------------------------------------------------------
@dataclass
class _Robot:
    odom: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    last_odom: tuple[float, float, float] | None = None
    team: str | None = None
    path: list[tuple[int, float, float, float]] = field(default_factory=list)
    path_sent_ns: int = -PATH_PERIOD_NS


def _between(a: tuple[float, float, float], b: tuple[float, float, float]
             ) -> tuple[float, float, float]:
    """T_map_odom from T_map_base = a and T_odom_base = b: a ⊕ b⁻¹."""
    yaw = a[2] - b[2]
    c, s = math.cos(yaw), math.sin(yaw)
    return (a[0] - (c * b[0] - s * b[1]), a[1] - (s * b[0] + c * b[1]),
            math.atan2(math.sin(yaw), math.cos(yaw)))


def export_recording(recording: Path, out: Path) -> dict[str, Any]:
    """Write the scans, odometry, estimates, trajectories and team maps of a recording."""
    from recording.reader import read_recording
    from schemas.codec import decode
    from schemas.errors import SchemaError
    from schemas.messages import MapUpdate, RobotStates, Scan

    rec = read_recording(recording)
    types: dict[str, type[Any]] = {"Scan": Scan, "MapUpdate": MapUpdate,
                                   "RobotStates": RobotStates}
    decoded: list[tuple[int, Any]] = []
    undecodable = 0
    for m in rec.messages:
        cls = types.get(m.type_name or "")
        if cls is None:
            continue
        try:
            msg = decode(m.data, cls)
        except SchemaError:
            undecodable += 1
            continue
        decoded.append((msg.stamp_ns or m.log_time_ns, msg))
    if not any(isinstance(msg, Scan) for _, msg in decoded):
        raise ExportError(f"{recording}: no Scan messages to export")
    decoded.sort(key=lambda sm: sm[0])
    robots: dict[str, _Robot] = {}
    with BagWriter(out) as bag:
        for stamp, msg in decoded:
            if isinstance(msg, Scan):
                _write_scan(bag, robots.setdefault(msg.robot_id, _Robot()), stamp, msg)
            elif isinstance(msg, RobotStates):
                _write_estimates(bag, robots, stamp, msg)
            else:
                _write_map(bag, stamp, msg)
        for rid, r in robots.items():
            _write_path(bag, rid, r, force=True)
        counts = dict(bag.counts)
    return {"recording": str(recording), "bag": str(out), "topics": counts,
            "messages": sum(counts.values()), "undecodable": undecodable,
            "unreadable": rec.report.unreadable_messages}


def _write_scan(bag: BagWriter, r: _Robot, stamp: int, msg: Any) -> None:
    rid = ros_name(msg.robot_id)
    x, y, yaw = (float(v) for v in msg.odom_pose)
    r.odom[stamp], r.last_odom = (x, y, yaw), (x, y, yaw)
    bag.tf(stamp, [bag.transform(stamp, f"{rid}/odom", f"{rid}/base_link", x, y, yaw)])
    bag.scan(f"/{rid}/scan", stamp, f"{rid}/base_link", msg.angle_min_rad,
             msg.angle_increment_rad, msg.range_min_m, msg.range_max_m, msg.ranges_m())


def _write_estimates(bag: BagWriter, robots: dict[str, _Robot], stamp: int, msg: Any) -> None:
    transforms = []
    for est in msg.robots:
        r = robots.setdefault(est.robot_id, _Robot())
        odom = r.odom.get(est.last_scan_stamp_ns, r.last_odom)
        if odom is None:
            continue
        team, rid = ros_name(est.team_id), ros_name(est.robot_id)
        pose = tuple(float(v) for v in est.pose)
        transforms.append(bag.transform(stamp, f"{team}/map", f"{rid}/odom",
                                        *_between(pose, odom)))   # type: ignore[arg-type]
        if r.team != team:   # a new map frame (a merge): the trajectory starts anew in it
            _write_path(bag, est.robot_id, r, force=True)
            r.team, r.path = team, []
        last = r.path[-1] if r.path else None
        if last is None or math.hypot(pose[0] - last[1], pose[1] - last[2]) >= PATH_STEP_M or \
                abs(math.remainder(pose[2] - last[3], 2 * math.pi)) >= PATH_STEP_RAD:
            r.path.append((stamp, *pose))   # type: ignore[arg-type]
        if stamp - r.path_sent_ns >= PATH_PERIOD_NS:
            _write_path(bag, est.robot_id, r)
    if transforms:
        bag.tf(stamp, transforms)


def _write_path(bag: BagWriter, robot_id: str, r: _Robot, force: bool = False) -> None:
    if not r.path or r.team is None:
        return
    stamp = r.path[-1][0]
    if not force and stamp - r.path_sent_ns < PATH_PERIOD_NS:
        return
    frame = f"{r.team}/map"
    poses = [bag.t["geometry_msgs/msg/PoseStamped"](header=bag.header(s, frame),
                                                    pose=bag.pose(x, y, yaw))
             for s, x, y, yaw in r.path]
    bag.write(f"/{ros_name(robot_id)}/path", "nav_msgs/msg/Path", stamp,
              bag.t["nav_msgs/msg/Path"](header=bag.header(stamp, frame), poses=poses))
    r.path_sent_ns = stamp


def _write_map(bag: BagWriter, stamp: int, msg: Any) -> None:
    team = ros_name(msg.team_id)
    t = bag.t
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=bag.header(stamp, "").stamp, resolution=float(msg.resolution_m),
        width=msg.width, height=msg.height, origin=bag.pose(*msg.origin))
    bag.write(f"/map/{team}", "nav_msgs/msg/OccupancyGrid", stamp,
              t["nav_msgs/msg/OccupancyGrid"](header=bag.header(stamp, f"{team}/map"), info=info,
                                              data=msg.grid().reshape(-1).copy()))


# a CARMEN log -----------------------------------------------------------------------------
def export_carmen(log_file: Path, out: Path, laser: str = "front", odometry: str = "auto",
                  progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """The scans of one laser of a CARMEN log with the odometry ``slam-log`` would use: an
    ``Odometry`` of ``base_link`` at each scan's stamp and the laser's mount on ``/tf_static``
    (``PARAM robot_<laser>laser_offset``)."""
    from server.offline.logs import attach_odometry, choose_odometry_source, read_log, select_stream
    from server.offline.slam_log import laser_offset

    clog = read_log(log_file)
    lasers = select_stream(clog, laser)
    source = choose_odometry_source(lasers, clog.odometry, odometry)
    offset = laser_offset(clog, laser)
    scans = attach_odometry(lasers, clog.odometry, offset, source)
    with BagWriter(out) as bag:
        t0 = _stamp_ns(scans[0].record.stamp_text)
        bag.tf(t0, [bag.transform(t0, "base_link", "laser", offset, 0.0, 0.0)], static=True)
        for i, s in enumerate(scans):
            r = s.record
            stamp = _stamp_ns(r.stamp_text)
            lx, ly, lyaw = (float(v) for v in s.T_odom_laser)
            # the robot's pose is the laser's with the mount taken off
            x, y = lx - offset * math.cos(lyaw), ly - offset * math.sin(lyaw)
            t = bag.t
            bag.write("/odom", "nav_msgs/msg/Odometry", stamp, t["nav_msgs/msg/Odometry"](
                header=bag.header(stamp, "odom"), child_frame_id="base_link",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](
                    pose=bag.pose(x, y, lyaw), covariance=np.zeros(36)),
                twist=t["geometry_msgs/msg/TwistWithCovariance"](
                    twist=t["geometry_msgs/msg/Twist"](
                        linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                    covariance=np.zeros(36))))
            ranges = r.ranges_m
            # without a maximum in the log every reading is a return: a limit above them all
            range_max = r.max_range_m if r.max_range_m is not None else \
                float(np.max(ranges[np.isfinite(ranges)], initial=0.0)) + 1.0
            if r.max_range_m is not None:   # a reading at the maximum is no return
                ranges = np.where(ranges >= r.max_range_m, np.inf, ranges)
            bag.scan("/scan", stamp, "laser", r.angles_rad[0],
                     float(r.angles_rad[1] - r.angles_rad[0]) if len(ranges) > 1 else 0.0,
                     0.0, range_max, ranges)
            if progress is not None and i % 500 == 0:
                progress(i)
        counts = dict(bag.counts)
    return {"log": str(log_file), "bag": str(out), "odometry_source": source,
            "laser_offset_m": offset, "topics": counts, "messages": sum(counts.values())}


def _stamp_ns(text: str) -> int:
    """A CARMEN stamp as written (``1133296123.456789``) to integer nanoseconds, exactly."""
    whole, _, frac = text.partition(".")
    sign = -1 if whole.startswith("-") else 1
    return int(whole) * 1_000_000_000 + sign * int((frac + "0" * 9)[:9] or 0)
