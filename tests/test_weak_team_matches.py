"""A narrow robot's whole scan in a corridor, matched against its wide teammate's map: the match
says nothing along the corridor, but where the robot is across it and how it is turned; it is
kept for that (``cross_matches(hold_weak=True)``) and does not count as the maps tying the
robots (``GraphSurgery.tied_by_maps``)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import gtsam
import numpy as np

from schemas.se2 import between, compose
from server.config import ServerConfig
from server.fleet.model import Link
from server.rendezvous.maps import UNKNOWN_ALONG_SIGMA_M, cross_matches
from server.rendezvous.surgery import GraphSurgery
from server.slam import RobotSlam, SlamConfig
from server.slam.backend import FactorRecord
from tests.test_slam_synthetic import Segment, drive, waypoints_path

#: a misplacement of b's map in a's: 0.3 m along the corridor, 0.08 m across, turned 1.8°
MISPLACED = np.array([0.3, 0.08, math.radians(1.8)])


def corridor() -> list[Segment]:
    """Two walls 2 m apart, 40 m long: from its middle a 360° LIDAR sees no end."""
    return [((-20.0, -1.0), (20.0, -1.0)), ((-20.0, 1.0), (20.0, 1.0))]


def robot(path: list[tuple[float, float]], name: str) -> tuple[RobotSlam, np.ndarray]:
    truth = waypoints_path(path, 0.2)
    d = drive(corridor(), truth, odom_drift_rad_per_m=0.0, odom_scale=1.0, seed=len(name))
    slam = RobotSlam(name, SlamConfig())
    for i, (odom, ranges) in enumerate(zip(d.odom, d.ranges, strict=True)):
        slam.add_scan(i * 100_000_000, odom, ranges, d.angles)
    return slam, truth


def test_a_corridor_match_keeps_its_turn_and_its_offset_across_but_not_along() -> None:
    a, truth_a = robot([(-4.0, 0.0), (4.0, 0.0)], "a")
    b, truth_b = robot([(-3.0, 0.1), (3.0, 0.1)], "b")
    right = between(truth_a[0], truth_b[0])            # b's frame in a's
    T_ab = compose(right, MISPLACED)                   # a start placed off by MISPLACED
    kb = len(b.keyframes) // 2
    # plain: the corridor's match is degenerate and left out
    assert cross_matches(a, b, T_ab=T_ab, only=[kb]) == []
    (m,) = cross_matches(a, b, T_ab=T_ab, only=[kb], hold_weak=True)
    assert m.weak and m.kb == kb
    placed = compose(T_ab, b.keyframe_pose(kb))
    found = compose(a.keyframe_pose(m.ka), m.T_ka_kb)
    true = compose(right, b.keyframe_pose(kb))         # b's own map is exact here
    # across the corridor (y) and in heading: where the truth is
    assert abs(found[1] - true[1]) < 0.02
    assert abs(math.degrees(found[2] - true[2])) < 0.3
    # along it (x): where it was placed, not where the truth is (0.3 m from it)
    assert abs(found[0] - placed[0]) < 0.02 and abs(placed[0] - true[0]) > 0.25
    # and its factor knows nothing along it: its weakest direction (in kb's frame) is the
    # corridor's axis, within the degree a's own map may be turned by
    w, v = np.linalg.eigh(m.information[:2, :2])
    assert w[0] <= 1.01 / UNKNOWN_ALONG_SIGMA_M ** 2 and w[1] > 1e3   # across: σ under 3 cm
    off = abs(math.degrees(math.atan2(v[1, 0], v[0, 0]) - found[2])) % 180
    assert min(off, 180.0 - off) < 1.0


def link(kind: str) -> Link:
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 0.1)
    f = gtsam.BetweenFactorPose2(1, 2, gtsam.Pose2(), noise)
    return Link("r1", "r2", 0, FactorRecord(f, kind))


def test_weak_matches_do_not_tie_the_maps() -> None:
    cfg = ServerConfig()
    need = cfg.teams.retire_sightings_after
    assert need > 0
    surgery = SimpleNamespace(cfg=cfg)
    weak = [link("cross_weak") for _ in range(need + 3)]
    assert not GraphSurgery.tied_by_maps(surgery, weak, "r1", "r2")  # type: ignore[arg-type]
    full = [link("cross") for _ in range(need)]
    assert GraphSurgery.tied_by_maps(surgery, weak + full, "r2", "r1")  # type: ignore[arg-type]
