"""ROS 2 bags out (``mrslam export --ros2``) and ROS bags in (``slam-log`` on a bag): what is
written reads back with rosbags and with the mcap library, every message decoding to its ROS
type; a CARMEN log through a bag gives slam-log the same laser poses, hence the same map."""

from __future__ import annotations

import bz2
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from mrslam.ros2 import BagWriter, ExportError, export_carmen, export_recording, ros_name
from recording.writer import McapRecorder
from schemas import keys
from schemas.codec import encode
from schemas.messages import MapUpdate, RobotEstimate, RobotStates, Scan, quantise_ranges_mm
from server.offline.logs import attach_odometry, choose_odometry_source, read_log, select_stream
from server.offline.logs.rosbag import BagError, compose, read_bag, yaw_of
from server.offline.slam_log import laser_offset
from server.offline.slam_log import run as slam_log
from tests.conftest import DATA

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

CARMEN = DATA / "carmen"
T0 = 1_700_000_000_000_000_000


def small_recording(path: Path) -> None:
    """Two robots scanning for 2 s, their estimates, a team map; beams 0 and 3 no return."""
    with McapRecorder(path) as rec:
        for k in range(20):
            stamp = T0 + k * 100_000_000
            for j, rid in enumerate(("r1", "r2")):
                ranges = np.full(90, 3.0)
                ranges[[0, 3]] = np.inf
                scan = Scan(robot_id=rid, seq=k, stamp_ns=stamp, angle_min_rad=-math.pi / 2,
                            angle_increment_rad=math.pi / 90, range_min_mm=100,
                            range_max_mm=12000, ranges_mm=quantise_ranges_mm(ranges),
                            odom_pose=(0.1 * k, float(j), 0.01 * k))
                rec.add(keys.robot_scan(rid), encode(scan), receive_ns=stamp)
            states = RobotStates(seq=k, stamp_ns=stamp + 1, robots=[
                RobotEstimate(robot_id=rid, team_id=f"team-{rid}", pose=(1 + 0.1 * k, j, 0.0),
                              last_scan_stamp_ns=stamp) for j, rid in enumerate(("r1", "r2"))])
            rec.add(keys.SERVER_ROBOTS, encode(states), receive_ns=stamp + 1)
        grid = np.full((20, 30), -1, dtype=np.int8)
        grid[5:10, 5:10] = 0
        grid[5, 5:10] = 100
        m = MapUpdate.from_grid(grid, team_id="team-r1", robot_ids=["r1"], resolution_m=0.05,
                                origin=(-1.0, -0.5, 0.0), stamp_ns=T0 + 5)
        rec.add(keys.SERVER_MAP, encode(m), receive_ns=T0 + 5)


def mcap_messages(bag: Path) -> list[tuple[str, str, object]]:
    """Every message of the bag's MCAP file, read by the mcap library and decoded (CDR) by
    the ROS type its schema names."""
    store = get_typestore(Stores.ROS2_JAZZY)
    (file,) = bag.glob("*.mcap")
    out = []
    with file.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schema is not None and channel.message_encoding == "cdr"
            out.append((channel.topic, schema.name,
                        store.deserialize_cdr(message.data, schema.name)))
    return out


def test_a_recording_exports_to_standard_ros2_types(tmp_path: Path) -> None:
    small_recording(tmp_path / "run.mcap")
    summary = export_recording(tmp_path / "run.mcap", tmp_path / "bag")
    with AnyReader([tmp_path / "bag"]) as reader:
        types = {t: i.msgtype for t, i in reader.topics.items()}
        decoded = [(c.topic, reader.deserialize(raw, c.msgtype))
                   for c, _, raw in reader.messages()]
    assert types == {"/r1/scan": "sensor_msgs/msg/LaserScan",
                     "/r2/scan": "sensor_msgs/msg/LaserScan", "/tf": "tf2_msgs/msg/TFMessage",
                     "/r1/path": "nav_msgs/msg/Path", "/r2/path": "nav_msgs/msg/Path",
                     "/map/team_r1": "nav_msgs/msg/OccupancyGrid"}
    assert len(decoded) == summary["messages"]
    scans = [m for t, m in decoded if t == "/r1/scan"]
    assert len(scans) == 20 and scans[0].header.frame_id == "r1/base_link"
    r = scans[0].ranges
    assert np.isposinf(r[[0, 3]]).all() and np.allclose(np.delete(r, [0, 3]), 3.0)  # REP 117
    assert scans[0].range_max == pytest.approx(12.0) and scans[0].range_min == pytest.approx(0.1)
    (grid,) = [m for t, m in decoded if t.startswith("/map/")]
    assert (grid.info.width, grid.info.height) == (30, 20)
    assert grid.data.reshape(20, 30)[5, 7] == 100
    assert grid.header.frame_id == "team_r1/map" and grid.info.origin.position.x == -1.0
    # map -> odom -> base_link places the robot where the server estimated it
    tfs = [tr for t, m in decoded if t == "/tf" for tr in m.transforms]
    map_odom = [tr for tr in tfs if tr.child_frame_id == "r1/odom"][-1]
    assert map_odom.header.frame_id == "team_r1/map"
    tr = map_odom.transform
    T_map_odom = np.array([tr.translation.x, tr.translation.y, yaw_of(tr.rotation)])
    k = 19   # the last estimate: (1 + 0.1k, 0, 0) with the odometry (0.1k, 0, 0.01k)
    assert np.allclose(compose(T_map_odom, np.array([0.1 * k, 0.0, 0.01 * k])),
                       [1 + 0.1 * k, 0.0, 0.0])
    # the mcap library reads the same messages, each decoding to its ROS type
    via_mcap = mcap_messages(tmp_path / "bag")
    assert len(via_mcap) == len(decoded)
    assert {(t, s) for t, s, _ in via_mcap} >= {("/r1/scan", "sensor_msgs/msg/LaserScan"),
                                                 ("/map/team_r1", "nav_msgs/msg/OccupancyGrid")}


def test_a_carmen_log_through_a_bag_gives_slam_log_the_same_laser_poses(tmp_path: Path
                                                                        ) -> None:
    log_file = CARMEN / "mit-csail.clf.bz2"
    export_carmen(log_file, tmp_path / "bag")
    clog = read_log(log_file)
    lasers = select_stream(clog)
    scans = attach_odometry(lasers, clog.odometry, laser_offset(clog, "front"),
                            choose_odometry_source(lasers, clog.odometry))
    blog, info = read_bag(tmp_path / "bag")
    assert "/odom" in info.source and len(blog.lasers) == len(scans) == 1988
    for s, b in zip(scans, blog.lasers, strict=True):
        assert b.stamp_s == pytest.approx(s.record.stamp_s, abs=1e-9)
        assert b.laser_pose is not None
        assert np.allclose(b.laser_pose, s.T_odom_laser, atol=1e-9)
        assert np.allclose(b.ranges_m, s.record.ranges_m, rtol=1e-6)
        assert np.allclose(b.angles_rad, s.record.angles_rad, atol=1e-6)
    assert len(mcap_messages(tmp_path / "bag")) == 2 * 1988 + 1


def test_slam_log_on_a_bag_writes_the_map_of_the_log(tmp_path: Path) -> None:
    """The first 300 scans of a real log, as a log and as a bag: the same poses until a
    keyframe decision tips the other way (LaserScan's beam angles are float32: 4e-8 rad off
    CARMEN's), and then close."""
    short = tmp_path / "short.clf"
    lines, scans = [], 0
    with bz2.open(CARMEN / "mit-csail.clf.bz2", "rt") as f:
        for line in f:
            scans += line.startswith("FLASER")
            if scans > 300:
                break
            lines.append(line)
    short.write_text("".join(lines))
    export_carmen(short, tmp_path / "bag")
    a = slam_log(short, tmp_path / "from-log")
    b = slam_log(tmp_path / "bag", tmp_path / "from-bag")
    assert a["scans"] == b["scans"] == 300 and b["laser"] == "LaserScan"
    pa = np.loadtxt(tmp_path / "from-log" / "poses.txt")
    pb = np.loadtxt(tmp_path / "from-bag" / "poses.txt")
    assert np.allclose(pa[:, 0], pb[:, 0], atol=1e-6)
    assert np.abs(pa[:50, 1:] - pb[:50, 1:]).max() < 1e-6
    assert np.abs(pa[:, 1:3] - pb[:, 1:3]).max() < 0.5
    assert (tmp_path / "from-bag" / "map.yaml").is_file()


def test_a_ros1_bag_with_tf_odometry_and_a_mounted_laser(tmp_path: Path) -> None:
    from rosbags.rosbag1 import Writer

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                      "tf2_msgs/msg/TFMessage"))
    t = store.types

    def header(k: int, frame: str) -> object:
        return t["std_msgs/msg/Header"](seq=k, stamp=t["builtin_interfaces/msg/Time"](
            sec=100 + k, nanosec=0), frame_id=frame)

    def tf(k: int, parent: str, child: str, x: float, yaw: float) -> object:
        return t["geometry_msgs/msg/TransformStamped"](
            header=header(k, parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                           w=math.cos(yaw / 2))))

    path = tmp_path / "run.bag"
    with Writer(path) as w:
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
        c_scan = w.add_connection("/base_scan", "sensor_msgs/msg/LaserScan", typestore=store)
        msg = t["tf2_msgs/msg/TFMessage"](transforms=[tf(0, "base_link", "laser", 0.2, 0.0)])
        w.write(c_static, 100 * 10**9, store.serialize_ros1(msg, "tf2_msgs/msg/TFMessage"))
        for k in range(5):
            msg = t["tf2_msgs/msg/TFMessage"](transforms=[tf(k, "odom", "base_link", 1.0 * k,
                                                             math.pi / 2)])
            w.write(c_tf, (100 + k) * 10**9,
                    store.serialize_ros1(msg, "tf2_msgs/msg/TFMessage"))
            ranges = np.array([1.0, np.nan, -np.inf, 50.0, 2.0], dtype=np.float32)
            scan = t["sensor_msgs/msg/LaserScan"](
                header=header(k, "laser"), angle_min=-0.5, angle_max=0.5, angle_increment=0.25,
                time_increment=0.0, scan_time=0.0, range_min=0.1, range_max=30.0,
                ranges=ranges, intensities=np.zeros(0, dtype=np.float32))
            w.write(c_scan, (100 + k) * 10**9,
                    store.serialize_ros1(scan, "sensor_msgs/msg/LaserScan"))
    blog, info = read_bag(path)
    assert info.source.startswith("/base_scan") and "/tf (base_link in odom)" in info.source
    assert info.laser_pose_from == "/tf_static" and info.laser_pose == [0.2, 0.0, 0.0]
    assert len(blog.lasers) == 5
    last = blog.lasers[-1]
    assert np.allclose(last.laser_pose, [4.0, 0.2, math.pi / 2])   # the mount, turned
    assert last.stamp_text == "104.000000000"
    assert np.isinf(last.ranges_m[[1, 2, 3]]).all() and last.ranges_m[0] == 1.0


def test_bad_bags_are_named_errors(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such file"):
        read_bag(tmp_path / "missing.bag")
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(BagError, match="not a ROS bag"):
        read_bag(tmp_path / "junk.bag")
    small_recording(tmp_path / "run.mcap")
    export_recording(tmp_path / "run.mcap", tmp_path / "bag")
    with pytest.raises(BagError, match="no topic '/nope'"):
        read_bag(tmp_path / "bag", scan_topic="/nope")
    with pytest.raises(BagError, match="carries nav_msgs/msg/Path"):
        read_bag(tmp_path / "bag", scan_topic="/r1/path")
    # an exported run reads back: its /tf carries each robot's odometry
    blog, info = read_bag(tmp_path / "bag", scan_topic="/r1/scan")
    assert len(blog.lasers) == 20 and "/tf (r1/base_link in r1/odom)" in info.source
    with BagWriter(tmp_path / "scans-only") as bag:
        bag.scan("/scan", T0, "laser", -1.0, 0.5, 0.1, 10.0, np.ones(5))
    # a bag of scans alone reads: its odometry will come from the scans
    blog, info = read_bag(tmp_path / "scans-only")
    assert info.odometry == "none: scan matching" and blog.lasers[0].laser_pose is None
    with pytest.raises(ExportError, match="exists already"):
        export_recording(tmp_path / "run.mcap", tmp_path / "bag")
    assert ros_name("team-r1") == "team_r1" and ros_name("1a") == "_1a"
