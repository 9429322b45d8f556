"""A robot whose agent reboots comes back with its odometry at zero, after a gap, perhaps a
little moved: the server keeps it in its map (the jump in odometry is taken for what it is,
and the scan is matched from where the robot was last), rather than start it afresh."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas import Scan
from schemas.messages import quantise_ranges_mm
from schemas.se2 import between, compose
from server.config import ServerConfig
from server.core import ServerCore
from tests.test_rendezvous_merger import BEAMS, WALLS, ranges_from

START = np.array([3.5, 3.0, math.pi / 2])


def run(push_rad: float, gap_s: float) -> tuple[ServerCore, list[float]]:
    """r1 circles; at scan 150 its agent reboots (alive flaps, odometry restarts at zero,
    ``gap_s`` without scans, the robot pushed ``push_rad`` along its circle)."""
    core = ServerCore(ServerConfig.model_validate({"robots": ["r1"]}), navigate=False)
    odom_origin, errors = START.copy(), []
    for k in range(300):
        a = 0.03 * k + (push_rad if k >= 150 else 0.0)
        pose = np.array([2.5 + math.cos(a), 3.0 + math.sin(a), a + math.pi / 2])
        stamp = k * 100_000_000 + (round(gap_s * 1e9) if k >= 150 else 0)
        if k == 150:
            odom_origin = pose.copy()
            core.set_alive("r1", False)
            core.set_alive("r1", True)
        odom = between(odom_origin, pose)
        core.on_scan(Scan(robot_id="r1", seq=k + 1 if k < 150 else k - 149, stamp_ns=stamp,
                          odom_pose=(float(odom[0]), float(odom[1]), float(odom[2])),
                          angle_min_rad=-math.pi, angle_increment_rad=2 * math.pi / BEAMS,
                          range_min_mm=50, range_max_mm=12000,
                          ranges_mm=quantise_ranges_mm(ranges_from(pose, WALLS), 0.05, 12.0)),
                     stamp)
        est = compose(START, core.robots["r1"].pose)
        errors.append(float(np.hypot(*(est[:2] - pose[:2]))))
    return core, errors


@pytest.mark.parametrize(("push_rad", "gap_s"), [(0.0, 0.0), (0.25, 5.0)])
def test_a_rebooted_robot_stays_in_its_map(push_rad: float, gap_s: float) -> None:
    core, errors = run(push_rad, gap_s)
    assert max(errors[:150]) < 0.02
    assert max(errors[150:]) < 0.05          # placed again at once, not at the origin
    r1 = core.robots["r1"]
    assert len(core.robots) == 1 and r1.slam.keyframes[0].stamp_ns == 0   # the same graph
    assert r1.alive and r1.scans == 300
