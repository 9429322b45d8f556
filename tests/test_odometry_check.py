"""Corrupt odometry samples are skipped and counted, and nothing else is
(``server.offline.logs.odomcheck``; ``slam-log`` on bags)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from mrslam.cli import app
from server.offline.logs.odomcheck import OdometryLimits, check_odometry
from server.offline.logs.rosbag import BagError, read_bag
from tests.bagbuild import OKO, Messages, Pose, Scan, write_bag

needs_bags = pytest.mark.skipif(not OKO.is_file(), reason="no ../shared/data/bags")


def drive(n: int, dt: float = 0.05, v: float = 0.5, w: float = 0.4) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """A robot driving an arc at v [m/s], w [rad/s], sampled every dt seconds."""
    t = 100.0 + dt * np.arange(n)
    th = w * (t - t[0])
    x, y = v / w * np.sin(th), v / w * (1 - np.cos(th))
    return t, np.stack([x, y, np.arctan2(np.sin(th), np.cos(th))], axis=1)


def test_spikes_are_skipped_by_reason_and_the_rest_kept() -> None:
    t, p = drive(200)
    p[20, 1] = 1.9e32            # a flipped bit
    p[50, 0] = np.nan
    p[80, :2] = 0.0              # fields read as zero: back at the origin for one sample
    p[120, 2] += 2.5             # the heading, for one sample
    p[121, 0] = -3.0e7           # farther than any place on Earth
    check = check_odometry(t, p)
    assert dict(check.skipped) == {"absurd": 2, "non_finite": 1, "jump": 2}
    assert check.keep == [i for i in range(200) if i not in (20, 50, 80, 120, 121)]


def test_a_jump_the_odometry_goes_on_from_is_kept() -> None:
    """A driver restarted at zero, or odometry that stalled and caught up: what the robot's
    odometry said, not corrupt."""
    t, p = drive(100)
    p[60:] -= p[60]              # restarted at the origin
    check = check_odometry(t, p)
    assert check.keep == list(range(100)) and check.skipped_total == 0


def test_a_burst_of_differently_corrupt_samples_is_skipped() -> None:
    t, p = drive(100)
    p[40, 1] = 0.0
    p[41, 0] = -p[41, 0]
    p[41, 2] = 0.0
    p[42, 2] = p[42, 2] + math.pi
    check = check_odometry(t, p)
    assert check.skipped["jump"] == 3 and 40 not in check.keep and 43 in check.keep


def test_a_corrupt_first_sample_is_skipped() -> None:
    t, p = drive(50)
    p[0, :2] = [4.0, -3.0]
    assert check_odometry(t, p).keep == list(range(1, 50))


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 4.5), st.floats(-5.0, 5.0), st.floats(0.01, 0.5),
       st.integers(2, 120))
def test_a_robot_within_its_limits_loses_no_sample(v: float, w: float, dt: float,
                                                   n: int) -> None:
    t, p = drive(n, dt, v, w if abs(w) > 1e-3 else 1e-3)
    assert check_odometry(t, p, OdometryLimits()).keep == list(range(n))


def small_bag(path: Path, poses: list[Pose], ros2: str | None = None) -> Path:
    """Scans of a 4 × 3 m room seen from its middle, and the given odometry on /odom."""
    m = Messages(ros2 is not None)
    a = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    r = np.minimum(2.0 / np.maximum(np.abs(np.cos(a)), 1e-9), 1.5 / np.maximum(np.abs(np.sin(a)),
                                                                             1e-9))
    msgs = []
    for k in range(20):
        t = 10**9 * (50 + k) // 5
        s = Scan(t, -math.pi, 2 * math.pi / 360, 0.1, 10.0, r.astype(np.float32))
        msgs.append(("/scan", "sensor_msgs/msg/LaserScan", t, m.scan(s)))
    msgs += [("/odom", "nav_msgs/msg/Odometry", p.stamp_ns, m.odometry(p)) for p in poses]
    msgs.sort(key=lambda x: x[2])
    return write_bag(path, msgs, ros2)


@pytest.mark.parametrize("ros2", [None, "mcap", "sqlite3"])
def test_a_bag_whose_every_odometry_sample_is_corrupt_exits_2(tmp_path: Path,
                                                              ros2: str | None) -> None:
    poses = [Pose(10**9 * (50 + k) // 5, 1e30 * (k + 1), float("nan") if k % 2 else 0.0, 0.0)
             for k in range(20)]
    bag = small_bag(tmp_path / ("run.bag" if ros2 is None else "run"), poses, ros2)
    with pytest.raises(BagError, match="every odometry sample of /odom"):
        read_bag(bag)
    res = CliRunner().invoke(app, ["slam-log", str(bag), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and "Traceback" not in res.output
    line = [ln for ln in res.output.splitlines() if ln.startswith("mrslam:")]
    assert len(line) == 1 and "corrupt" in line[0]


@pytest.mark.parametrize("ros2", [None, "mcap"])
def test_corrupt_samples_in_a_bag_are_counted_in_the_summary(tmp_path: Path,
                                                             ros2: str | None) -> None:
    poses = [Pose(10**9 * (195 + k) // 20, 0.0, 0.0, 0.0) for k in range(80)]   # 9.75-13.7 s
    poses[10] = Pose(poses[10].stamp_ns, 0.0, 1.9e32, 0.0)
    poses[30] = Pose(poses[30].stamp_ns, 0.7, 0.0, 0.0)
    bag = small_bag(tmp_path / ("run.bag" if ros2 is None else "run"), poses, ros2)
    res = CliRunner().invoke(app, ["slam-log", str(bag), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["bag"]["odometry_samples"] == 80
    assert summary["bag"]["odometry_skipped"] == {"absurd": 1, "jump": 1}
    assert summary["scans"] == 20
    assert "2 of 80 odometry samples" in res.output     # logged, once
    poses_out = np.loadtxt(tmp_path / "out" / "poses.txt")
    assert np.abs(poses_out[:, 1:]).max() < 0.05          # the robot stood still


@needs_bags
def test_the_real_robots_corrupt_samples_are_skipped_and_counted(tmp_path: Path) -> None:
    """oko's /odom: eight samples with a coordinate beyond 2·10⁷ m (1.9e32, 5.9e22...), and
    nineteen where, for one or two samples, a coordinate reads zero or the heading flips."""
    res = CliRunner().invoke(app, ["slam-log", str(OKO), "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["bag"]["odometry_skipped"] == {"absurd": 8, "jump": 19}
    assert summary["bag"]["odometry_samples"] == 1190
    assert summary["scans"] == summary["scans_in_log"] == 291
