"""``slam-log`` on bags as users bring them: real bags without odometry or with a bare laser
frame, MultiEchoLaserScan, ROS 2 bags in both storages (with and without ``metadata.yaml``,
cut short), and every kind of bag that cannot map exiting 2 with one line."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from mrslam.cli import app
from schemas.se2 import compose
from server.offline.logs.rosbag import read_bag
from tests.bagbuild import FUSE, HOKUYO, OKO, Messages, Pose, Scan, real_scans, write_bag

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

needs_bags = pytest.mark.skipif(not FUSE.is_file(), reason="no ../shared/data/bags")


def slam_log(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["slam-log", *args])
    return res.exit_code, res.output


def summary(out: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((out / "summary.json").read_text())
    return data


@needs_bags
@pytest.mark.parametrize("bag", [FUSE, OKO, HOKUYO], ids=lambda p: p.stem)
def test_every_shared_bag_maps_every_scan(tmp_path: Path, bag: Path) -> None:
    code, output = slam_log(str(bag), "--out", str(tmp_path))
    assert code == 0, output
    s = summary(tmp_path)
    assert s["scans"] == s["scans_in_log"] and s["scans_posed_percent"] == 100.0
    grid = np.asarray(Image.open(tmp_path / "map.png"))
    assert (grid == 0).sum() > 50 and (grid == 254).sum() > 200   # walls, free space


@needs_bags
def test_scan_matched_odometry_agrees_with_the_wheels(tmp_path: Path) -> None:
    """The TurtleBot3 bag mapped from its scans alone (as a bag without odometry is) and with
    its wheel odometry: the same trajectory within a centimetre."""
    assert slam_log(str(FUSE), "--out", str(tmp_path / "odom"))[0] == 0
    code, output = slam_log(str(FUSE), "--out", str(tmp_path / "scans"), "--odometry", "scans")
    assert code == 0, output
    s = summary(tmp_path / "scans")
    assert s["odometry_source"] == "/scan; odometry none: scan matching"
    so = s["scan_odometry"]
    assert isinstance(so, dict) and so["matched"] >= 0.99 * 456
    a = np.loadtxt(tmp_path / "odom" / "poses.txt")
    b = np.loadtxt(tmp_path / "scans" / "poses.txt")
    assert np.array_equal(a[:, 0], b[:, 0])
    assert np.hypot(*(a[:, 1:3] - b[:, 1:3]).T).max() < 0.01


def echoes_of(r: np.ndarray) -> list[list[float]]:
    """Two echoes where a beam has a return (the wall, and 1 m behind it), none otherwise."""
    return [[float(v), float(v) + 1.0] if math.isfinite(v) else [] for v in r]


@needs_bags
@pytest.mark.parametrize("ros2", [None, "mcap"])
def test_multi_echo_scans_give_the_first_echo_or_the_last(tmp_path: Path,
                                                          ros2: str | None) -> None:
    m = Messages(ros2 is not None)
    scans, poses = real_scans(60)
    odom = [("/odom", "nav_msgs/msg/Odometry", p.stamp_ns, m.odometry(p)) for p in poses]
    single = [("/scan", "sensor_msgs/msg/LaserScan", s.stamp_ns, m.scan(s)) for s in scans]
    multi = [("/horizontal_laser_2d", "sensor_msgs/msg/MultiEchoLaserScan", s.stamp_ns,
              m.multi_echo(s, echoes_of(s.ranges))) for s in scans]
    name = "{}.bag" if ros2 is None else "{}"
    a = write_bag(tmp_path / name.format("single"), sorted(single + odom, key=lambda x: x[2]),
                  ros2)
    b = write_bag(tmp_path / name.format("multi"), sorted(multi + odom, key=lambda x: x[2]),
                  ros2)
    one, _ = read_bag(a)
    first, info = read_bag(b)
    last, _ = read_bag(b, echo="last")
    assert info.scan_type == "sensor_msgs/msg/MultiEchoLaserScan"
    for s, f, la in zip(one.lasers, first.lasers, last.lasers, strict=True):
        assert np.array_equal(s.ranges_m, f.ranges_m)
        ok = np.isfinite(s.ranges_m) & (s.ranges_m + 1.0 <= 3.5)   # within range_max
        assert np.allclose(la.ranges_m[ok], s.ranges_m[ok] + 1.0, atol=1e-5)
    for out, bag, extra in (("single", a, []), ("first", b, []),
                            ("last", b, ["--echo", "last"])):
        code, output = slam_log(str(bag), "--out", str(tmp_path / out), *extra)
        assert code == 0, output
    assert summary(tmp_path / "first")["laser"] == "MultiEchoLaserScan"
    pa, pf = (np.loadtxt(tmp_path / n / "poses.txt") for n in ("single", "first"))
    assert np.array_equal(pa, pf)
    assert (tmp_path / "last" / "config.yaml").read_text().count("echo: last") == 1


@needs_bags
def test_laser_pose_option_places_the_laser_on_the_robot(tmp_path: Path) -> None:
    """The TurtleBot3 bag has no static transform for its laser (it sits 3.2 cm behind the
    robot's centre on a TurtleBot3 Burger)."""
    plain, info = read_bag(FUSE)
    assert info.laser_pose_from == "none: the robot's origin"
    mount = np.array([-0.032, 0.0, 0.0])
    given, info = read_bag(FUSE, laser_pose=mount)
    assert info.laser_pose_from == "--laser-pose" and info.laser_pose == [-0.032, 0.0, 0.0]
    for a, b in zip(plain.lasers, given.lasers, strict=True):
        assert a.robot_pose is not None and b.laser_pose is not None
        assert np.allclose(b.laser_pose, compose(a.robot_pose, mount))
    code, output = slam_log(str(FUSE), "--out", str(tmp_path), "--laser-pose=-0.032,0,0")
    assert code == 0, output
    bag = summary(tmp_path)["bag"]
    assert isinstance(bag, dict) and bag["laser_pose"] == [-0.032, 0.0, 0.0]
    code, output = slam_log(str(FUSE), "--out", str(tmp_path), "--laser-pose", "0.1,0")
    assert code == 2 and output.count("mrslam:") == 1 and "X,Y,YAW" in output


def room_scan(m: Messages, t: int, x: float) -> tuple[str, str, int, object]:
    """A 360° scan of a 6 × 4 m room from (x, 0), facing +x."""
    a = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        rx = np.where(c > 0, (3.0 - x) / c, np.where(c < 0, (-3.0 - x) / c, np.inf))
        ry = np.where(s != 0, 2.0 / np.abs(s), np.inf)
    ranges = np.minimum(rx, ry).astype(np.float32)
    return ("/scan", "sensor_msgs/msg/LaserScan", t,
            m.scan(Scan(t, -math.pi, 2 * math.pi / 360, 0.1, 10.0, ranges)))


@pytest.mark.parametrize("ros2", ["mcap", "sqlite3"])
def test_ros2_bags_with_tf_odometry_or_none(tmp_path: Path, ros2: str) -> None:
    """A robot driving 1 m along a room: odometry from /tf with the laser mounted 0.1 m ahead
    by /tf_static; and the same scans alone, placed by scan matching; and the storage file
    alone, without metadata.yaml."""
    m = Messages(True)
    scans = [room_scan(m, 10**9 + k * 10**8, 0.05 * k) for k in range(21)]
    tf = [("/tf", "tf2_msgs/msg/TFMessage", t,
           m.tf([("odom", "base_link", Pose(t, 0.05 * k - 0.1, 0.0, 0.0))]))
          for k, t in enumerate(s[2] for s in scans)]
    static = [("/tf_static", "tf2_msgs/msg/TFMessage", 10**9,
               m.tf([("base_link", "laser", Pose(10**9, 0.1, 0.0, 0.0))]))]
    with_tf = write_bag(tmp_path / "tf", sorted(static + tf + scans, key=lambda x: x[2]), ros2)
    blog, info = read_bag(with_tf)
    assert info.odometry == "/tf (base_link in odom)" and info.laser_pose == [0.1, 0.0, 0.0]
    assert np.allclose([np.asarray(r.laser_pose) for r in blog.lasers],
                       [[0.05 * k, 0.0, 0.0] for k in range(21)])
    bare = write_bag(tmp_path / "bare", scans, ros2)
    for bag in (bare, next(f for f in bare.iterdir() if f.suffix in (".mcap", ".db3"))):
        out = tmp_path / f"out-{bag.name}"
        code, output = slam_log(str(bag), "--out", str(out))
        assert code == 0, output
        poses = np.loadtxt(out / "poses.txt")
        assert len(poses) == 21 and summary(out)["scan_odometry"] is not None
        assert np.allclose(poses[:, 1], 0.05 * np.arange(21), atol=0.02)
    (bare / "metadata.yaml").unlink()
    code, output = slam_log(str(bare), "--out", str(tmp_path / "no-meta"))
    assert code == 0, output
    reader = summary(tmp_path / "no-meta")["bag"]
    assert isinstance(reader, dict) and "no metadata.yaml" in str(reader["reader"])


@needs_bags
def test_a_ros2_mcap_cut_short_maps_its_intact_chunks(tmp_path: Path) -> None:
    m = Messages(True)
    scans, poses = real_scans()
    msgs = [("/scan", "sensor_msgs/msg/LaserScan", s.stamp_ns, m.scan(s)) for s in scans]
    msgs += [("/odom", "nav_msgs/msg/Odometry", p.stamp_ns, m.odometry(p)) for p in poses]
    for _ in range(3):     # ballast, so that the file has several 1 MB chunks
        msgs += [("/ballast", "sensor_msgs/msg/LaserScan", s.stamp_ns, m.scan(s))
                 for s in scans]
    bag = write_bag(tmp_path / "bag", sorted(msgs, key=lambda x: x[2]), "mcap")
    (file,) = bag.glob("*.mcap")
    data = file.read_bytes()
    file.write_bytes(data[:len(data) * 7 // 10])   # killed while recording
    code, output = slam_log(str(bag), "--out", str(tmp_path / "out"), "--scan-topic", "/scan")
    assert code == 0, output
    s = summary(tmp_path / "out")
    assert s["stream_truncated"] and 0.3 * len(scans) < s["scans"] < len(scans)
    assert s["scans"] == s["scans_in_log"]


def one_line_failure(output: str) -> str:
    lines = [ln for ln in output.splitlines() if ln.startswith("mrslam:")]
    assert len(lines) == 1 and "Traceback" not in output, output
    return lines[0]


def test_bags_that_cannot_map_exit_2_with_one_line(tmp_path: Path) -> None:
    m = Messages(False)
    write_bag(tmp_path / "odom-only.bag", [
        ("/odom", "nav_msgs/msg/Odometry", 10**9 + k, m.odometry(Pose(10**9 + k, 0, 0, 0)))
        for k in range(5)])
    scans = write_bag(tmp_path / "scans.bag", [room_scan(m, 10**9 + k * 10**8, 0.0)
                                               for k in range(40)])
    data = scans.read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[:200])
    (tmp_path / "empty.bag").write_bytes(b"")
    (tmp_path / "folder").mkdir()
    (tmp_path / "ros2").mkdir()
    (tmp_path / "ros2" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tmp_path / "ros2" / "ros2_0.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\0" * 50)
    (tmp_path / "ros1-v12.bag").write_bytes(b"#ROSBAG V1.2\n" + b"\0" * 100)
    cases = {"empty.bag": "empty file", "cut.bag": "the bag is damaged",
             "folder": "is a directory", "odom-only.bag": "no sensor_msgs/LaserScan",
             "ros2": "the bag is damaged", "ros1-v12.bag": "format 1.2"}
    for name, what in cases.items():
        code, output = slam_log(str(tmp_path / name), "--out", str(tmp_path / "out"))
        assert code == 2, (name, output)
        assert what in one_line_failure(output), (name, output)



def test_a_vertical_scanner_is_not_taken_for_the_map(tmp_path: Path) -> None:
    """Cartographer's backpack bags carry a horizontal and a vertical multi-echo scanner."""
    m = Messages(False)
    msgs = []
    for k in range(30):
        t = 10**9 + k * 10**8
        _, _, _, scan = room_scan(m, t, 0.0)
        ranges = np.asarray(scan.ranges)  # type: ignore[attr-defined]
        s = Scan(t, -math.pi, 2 * math.pi / 360, 0.1, 10.0, ranges)
        msgs.append(("/horizontal_laser_2d", "sensor_msgs/msg/MultiEchoLaserScan", t,
                     m.multi_echo(s, [[float(r)] for r in ranges])))
        for j in range(2):   # the vertical one sends more
            msgs.append(("/vertical_laser_2d", "sensor_msgs/msg/MultiEchoLaserScan", t + j,
                         m.multi_echo(s, [[1.0]] * 360)))
    blog, info = read_bag(write_bag(tmp_path / "backpack.bag", msgs))
    assert info.scan_topic == "/horizontal_laser_2d" and len(blog.lasers) == 30


def test_fixed_joints_sent_on_tf_are_the_lasers_mount(tmp_path: Path) -> None:
    """Before /tf_static, a robot's fixed joints went out on /tf with every update."""
    m = Messages(False)
    msgs = []
    for k in range(20):
        t = 10**9 + k * 10**8
        msgs.append(("/tf", "tf2_msgs/msg/TFMessage", t, m.tf([
            ("odom", "base_link", Pose(t, 0.05 * k, 0.0, 0.0)),
            ("base_link", "laser", Pose(t, 0.15, 0.0, 0.0))])))
        msgs.append(room_scan(m, t, 0.05 * k + 0.15))
    blog, info = read_bag(write_bag(tmp_path / "old.bag", msgs))
    assert info.odometry == "/tf (base_link in odom)"
    assert info.laser_pose == [0.15, 0.0, 0.0]
    assert info.laser_pose_from == "/tf_static and /tf transforms that never change"
    assert np.allclose(np.asarray(blog.lasers[7].laser_pose), [0.5, 0.0, 0.0])


def test_odometry_on_another_clock_gives_way_to_scan_matching(tmp_path: Path) -> None:
    """Odometry stamped in simulated time beside scans stamped in wall time: nothing to
    interpolate, so the scans give the odometry."""
    m = Messages(True)
    scans = [room_scan(m, 1_700_000_000 * 10**9 + k * 10**8, 0.05 * k) for k in range(21)]
    odom = [("/odom", "nav_msgs/msg/Odometry", s[2],
             m.odometry(Pose(5 * 10**9 + k * 10**8, 0.05 * k, 0.0, 0.0)))
            for k, s in enumerate(scans)]
    bag = write_bag(tmp_path / "clocks", sorted(scans + odom, key=lambda x: x[2]), "mcap")
    code, output = slam_log(str(bag), "--out", str(tmp_path / "out"))
    assert code == 0, output
    s = summary(tmp_path / "out")
    assert "the odometry's stamps miss the scans" in s["odometry_source"]
    poses = np.loadtxt(tmp_path / "out" / "poses.txt")
    assert np.allclose(poses[:, 1], 0.05 * np.arange(21), atol=0.02)
