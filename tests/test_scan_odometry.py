"""Odometry from the scans alone (``server.offline.logs.scan_odometry``): known motions in a
room, the constant-velocity prediction where a scan cannot be matched, and a CARMEN log without any
odometry mapped by ``slam-log``."""

from __future__ import annotations

import bz2
import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mrslam.cli import app
from schemas.se2 import between, compose, wrap_angle
from server.offline.logs.scan_odometry import ScanOdometry
from tests.conftest import DATA

CARMEN = DATA / "carmen"
ANGLES = np.linspace(-math.pi, math.pi, 720, endpoint=False)


def room(pose: np.ndarray) -> np.ndarray:
    """Ranges seen from ``pose`` in an L-shaped room: a 6 × 4 m box with a 1 × 1 m pillar
    at (1.5, 1.0)."""
    x, y, th = pose
    a = ANGLES + th
    c, s = np.cos(a), np.sin(a)
    walls = [((-3, -2), (3, -2)), ((3, -2), (3, 2)), ((3, 2), (-3, 2)), ((-3, 2), (-3, -2)),
             ((1, 0.5), (2, 0.5)), ((2, 0.5), (2, 1.5)), ((2, 1.5), (1, 1.5)),
             ((1, 1.5), (1, 0.5))]
    best = np.full(len(a), np.inf)
    for (x1, y1), (x2, y2) in walls:
        ex, ey = x2 - x1, y2 - y1
        den = c * ey - s * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((x1 - x) * ey - (y1 - y) * ex) / den
            u = ((x1 - x) * s - (y1 - y) * c) / den
        hit = (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(hit & (t < best), t, best)
    return best


def test_a_known_motion_is_recovered_from_the_scans() -> None:
    """Driving an arc at 0.4 m/s and 0.5 rad/s, scanned at 10 Hz."""
    odo = ScanOdometry()
    truth = [np.array([-1.5, -0.8, 0.2])]
    for _ in range(40):
        truth.append(compose(truth[-1], np.array([0.04, 0.0, 0.05])))
    got = [odo.add(0.1 * k, room(T), ANGLES) for k, T in enumerate(truth)]
    for T, G in zip(truth, got, strict=True):
        rel_true, rel_got = between(truth[0], T), G
        assert np.hypot(*(rel_true[:2] - rel_got[:2])) < 0.02
        assert abs(wrap_angle(rel_true[2] - rel_got[2])) < math.radians(0.5)
    assert odo.stats.matched == 40 and odo.stats.predicted == 0


def test_a_scan_that_cannot_be_matched_takes_the_constant_velocity_prediction() -> None:
    odo = ScanOdometry()
    poses = [np.array([-1.0 + 0.05 * k, 0.0, 0.0]) for k in range(13)]
    got = [odo.add(0.1 * k, room(T), ANGLES) for k, T in enumerate(poses[:10])]
    blind = np.full(len(ANGLES), np.inf)        # the sensor covered for three scans
    got += [odo.add(0.1 * k, blind, ANGLES) for k in range(10, 13)]
    assert odo.stats.predicted == 3
    assert np.allclose([g[0] for g in got[10:]], [0.5, 0.55, 0.6], atol=0.01)


@pytest.mark.skipif(not CARMEN.is_dir(), reason="no ../shared/data/carmen")
def test_a_carmen_log_without_odometry_maps_from_its_scans(tmp_path: Path) -> None:
    """FR079's first 300 scans as bare ``LASER1`` lines (no pose, no ODOM lines)."""
    rows, n = [], 0
    with bz2.open(CARMEN / "fr079.clf.bz2", "rt") as f:
        for line in f:
            if line.startswith("FLASER"):
                w = line.split()
                k = int(w[1])
                rows.append(" ".join(["LASER1", *w[1:2 + k], *w[-3:]]) + "\n")
                n += 1
                if n == 300:
                    break
    log = tmp_path / "bare.clf"
    log.write_text("".join(rows))
    res = CliRunner().invoke(app, ["slam-log", str(log), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["scans"] == 300 and summary["odometry_source"] == "scans"
    assert summary["scan_odometry"]["matched"] >= 295
