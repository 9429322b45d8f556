"""Building small ROS 1 and ROS 2 bags for tests, with the rosbags writers: scans (single- or
multi-echo), odometry, transforms. Real scans come from the shared TurtleBot3 bag."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tests.conftest import DATA

BAGS = DATA / "bags"
FUSE = BAGS / "fuse-turtlebot3-sim.bag"
OKO = BAGS / "oko-real-lidar-odom.bag"
HOKUYO = BAGS / "scan-tools-hokuyo-demo.bag"


@dataclass(frozen=True)
class Scan:
    """One planar scan, free of any ROS type."""

    stamp_ns: int
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: np.ndarray


@dataclass(frozen=True)
class Pose:
    stamp_ns: int
    x: float
    y: float
    yaw: float


def real_scans(n: int | None = None) -> tuple[list[Scan], list[Pose]]:
    """The TurtleBot3 bag's first ``n`` scans and its odometry over the same time."""
    from rosbags.highlevel import AnyReader

    scans: list[Scan] = []
    poses: list[Pose] = []
    with AnyReader([FUSE]) as reader:
        conns = [c for c in reader.connections if c.topic in ("/scan", "/odom")]
        decoded: list[tuple[str, Any]] = [(c.msgtype, reader.deserialize(raw, c.msgtype))
                   for c, _, raw in reader.messages(connections=conns)]
    for ty, m in decoded:
        t = int(m.header.stamp.sec) * 10**9 + int(m.header.stamp.nanosec)
        if ty.endswith("LaserScan"):
            scans.append(Scan(t, float(m.angle_min), float(m.angle_increment),
                              float(m.range_min), float(m.range_max),
                              np.asarray(m.ranges, dtype=np.float32)))
        else:
            q = m.pose.pose.orientation
            poses.append(Pose(t, float(m.pose.pose.position.x), float(m.pose.pose.position.y),
                              math.atan2(2 * (q.w * q.z + q.x * q.y),
                                         1 - 2 * (q.y * q.y + q.z * q.z))))
    scans = scans[:n] if n is not None else scans
    end = scans[-1].stamp_ns
    return scans, [p for p in poses if p.stamp_ns <= end + 10**9]


class Messages:
    """Messages of one typestore (ROS 1 Noetic or ROS 2 Jazzy)."""

    def __init__(self, ros2: bool) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY if ros2 else Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        self.t = self.store.types
        self.ros2 = ros2

    def header(self, stamp_ns: int, frame: str) -> Any:
        sec, nsec = divmod(stamp_ns, 10**9)
        stamp = self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
        if self.ros2:
            return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
        return self.t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def quat(self, yaw: float) -> Any:
        return self.t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                      w=math.cos(yaw / 2))

    def scan(self, s: Scan, frame: str = "laser") -> Any:
        return self.t["sensor_msgs/msg/LaserScan"](
            header=self.header(s.stamp_ns, frame), angle_min=s.angle_min,
            angle_max=s.angle_min + s.angle_increment * (len(s.ranges) - 1),
            angle_increment=s.angle_increment, time_increment=0.0, scan_time=0.0,
            range_min=s.range_min, range_max=s.range_max,
            ranges=np.asarray(s.ranges, dtype=np.float32),
            intensities=np.zeros(0, dtype=np.float32))

    def multi_echo(self, s: Scan, echoes: Sequence[Sequence[float]], frame: str = "laser"
                   ) -> Any:
        """A MultiEchoLaserScan with the given echoes per beam (ranges of ``s`` unused)."""
        echo = self.t["sensor_msgs/msg/LaserEcho"]
        return self.t["sensor_msgs/msg/MultiEchoLaserScan"](
            header=self.header(s.stamp_ns, frame), angle_min=s.angle_min,
            angle_max=s.angle_min + s.angle_increment * (len(echoes) - 1),
            angle_increment=s.angle_increment, time_increment=0.0, scan_time=0.0,
            range_min=s.range_min, range_max=s.range_max,
            ranges=[echo(echoes=np.asarray(e, dtype=np.float32)) for e in echoes],
            intensities=[echo(echoes=np.zeros(0, dtype=np.float32)) for _ in echoes])

    def odometry(self, p: Pose, frame: str = "odom", child: str = "base_link") -> Any:
        t = self.t
        point = t["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=0.0)
        pose = t["geometry_msgs/msg/Pose"](position=point, orientation=self.quat(p.yaw))
        twist = t["geometry_msgs/msg/Twist"](
            linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0))
        return t["nav_msgs/msg/Odometry"](
            header=self.header(p.stamp_ns, frame), child_frame_id=child,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                             covariance=np.zeros(36)))

    def tf(self, transforms: Sequence[tuple[str, str, Pose]]) -> Any:
        """A TFMessage of (parent, child, pose of child in parent) transforms."""
        t = self.t
        return t["tf2_msgs/msg/TFMessage"](transforms=[
            t["geometry_msgs/msg/TransformStamped"](
                header=self.header(p.stamp_ns, parent), child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=p.x, y=p.y, z=0.0),
                    rotation=self.quat(p.yaw)))
            for parent, child, p in transforms])


def write_bag(path: Path, messages: Sequence[tuple[str, str, int, Any]], ros2: str | None = None,
              compression: str | None = None, chunk_bytes: int | None = None,
              store: Any = None) -> Path:
    """Write (topic, type, receive time [ns], message) as a ROS 1 bag, or a ROS 2 bag when
    ``ros2`` names the storage ("mcap" or "sqlite3"). Messages must be of ``Messages(ros2)``
    (whose ``store`` is given where it has types of its own)."""
    store = store or Messages(ros2 is not None).store
    if ros2 is None:
        from rosbags.rosbag1 import Writer as Writer1

        w1 = Writer1(path)
        if compression:
            w1.set_compression(getattr(Writer1.CompressionFormat, compression.upper()))
        if chunk_bytes:
            w1.chunk_threshold = chunk_bytes
        with w1:
            conns1: dict[str, Any] = {}
            for topic, ty, t, msg in messages:
                if topic not in conns1:
                    conns1[topic] = w1.add_connection(topic, ty, typestore=store)
                w1.write(conns1[topic], t, store.serialize_ros1(msg, ty))
        return path
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    plugin = StoragePlugin.MCAP if ros2 == "mcap" else StoragePlugin.SQLITE3
    with Writer2(path, version=9, storage_plugin=plugin) as w2:
        conns2: dict[str, Any] = {}
        for topic, ty, t, msg in messages:
            if topic not in conns2:
                conns2[topic] = w2.add_connection(topic, ty, typestore=store)
            w2.write(conns2[topic], t, store.serialize_cdr(msg, ty))
    return path
