"""A turning camera's whole scans: its views gathered while the robot stands still, the
stops the steering makes for them, their matches, and the reference heading the first gives
the square-wall ties — against the simulator's truth in the small house."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import between
from server.slam.config import SweepConfig
from server.slam.heading import SquareWalls
from server.slam.narrow import NarrowSensor
from server.slam.scan import ScanPoints
from server.slam.sweep import Sweep
from tests.test_slam_heading import keyframe_walls
from tests.test_slam_narrow import run

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

FOV = math.radians(87.0)


def view(heading: float, n: int = 20) -> ScanPoints:
    """A narrow view of a wall 2 m away, centred on ``heading`` (robot frame)."""
    a = heading + np.linspace(-FOV / 2, FOV / 2, n)
    pts = 2.0 * np.stack([np.cos(a), np.sin(a)], axis=1)
    nrm = -np.stack([np.cos(a), np.sin(a)], axis=1)
    return ScanPoints(pts, nrm, np.full(n, 2.0), pts.copy(), np.zeros((0, 2)), FOV, heading)


def test_the_views_of_one_turn_standing_still_are_one_whole_scan() -> None:
    sweep = Sweep(SweepConfig())
    odom = np.array([1.0, 2.0, 0.3])
    headings = [k * math.pi / 4 for k in range(8)]   # at rest and while turning
    got = [sweep.add(view(h), odom) for h in headings]
    n = next(i for i, g in enumerate(got) if g is not None) + 1
    assert 4 < n <= 8                       # nearly the whole circle: 87° views, 45° apart
    whole = got[n - 1]
    assert whole is not None and whole.fov_rad == pytest.approx(2 * math.pi)
    assert len(whole) == 20 * n and len(whole.hits) == 20 * n
    assert np.allclose(np.hypot(*whole.points.T), 2.0)        # in the robot's frame, unmoved
    assert sweep.wholes == 1
    # the robot moves a centimetre half way round: the views before it are not taken
    sweep = Sweep(SweepConfig())
    assert sweep.add(view(0.0), odom) is None
    assert sweep.add(view(math.pi / 2), odom) is None
    moved = odom + np.array([0.01, 0.0, 0.0])
    since = [sweep.add(view(h), moved) for h in headings[2:] + headings]
    whole = next(g for g in since if g is not None)
    # only the views since it moved, a turn round of them
    assert len(whole) == 20 * (since.index(whole) + 1) and since.index(whole) + 1 >= n


def test_a_robot_stops_at_its_start_and_every_metre_and_never_waits_for_ever() -> None:
    cfg = SweepConfig(every_m=1.0, wait_s=6.0)
    s = 1_000_000_000
    sweep = Sweep(cfg)
    # at the start, before it is known whether the camera turns
    assert sweep.due(0) and sweep.due(5 * s)
    odom = np.zeros(3)
    for k in range(8):
        sweep.add(view(k * math.pi / 4), odom)
    assert sweep.wholes == 1 and sweep.turning
    assert not sweep.due(6 * s)                  # it has its whole scan: drive on
    for x in np.arange(0.1, 1.05, 0.1):          # ... a metre
        sweep.add(view(0.0), np.array([x, 0.0, 0.0]))
        sweep.add(view(math.pi / 2), np.array([x, 0.0, 0.0]))
    assert sweep.due(10 * s)
    assert sweep.due(15 * s) and not sweep.due(17 * s)   # no whole scan in 6 s: give up
    assert sweep.given_up == 1 and not sweep.due(18 * s)
    # a camera that does not turn: it waits at the start, once, then never again
    fixed = Sweep(cfg)
    assert fixed.due(0)
    for i in range(70):
        fixed.add(view(0.0), np.array([0.05 * i, 0.0, 0.0]))
    assert not fixed.turning
    assert fixed.due(1 * s) and not fixed.due(8 * s) and not fixed.due(9 * s)
    assert not Sweep(SweepConfig(enabled=False)).due(0)


def test_a_tie_to_the_reference_holds_only_where_the_walls_agree_with_it() -> None:
    rng = np.random.default_rng(4)
    sq = SquareWalls(min_checked=3, agree_deg=3.0, max_correction_deg=8.0)
    sq.reference = (0, 0.0)
    for k in range(1, 5):
        sq.observe(k, keyframe_walls(0.0, 0.0, rng), lambda j: 0.0)
    assert sq.holds
    tied = sq.observe(5, keyframe_walls(math.radians(2), 0.0, rng), lambda j: 0.0)
    assert 0 in [j for j, _ in tied]
    # 5° off: the other partners still tie it, the reference does not
    tied = sq.observe(6, keyframe_walls(math.radians(5), 0.0, rng), lambda j: 0.0)
    assert tied and 0 not in [j for j, _ in tied]


def test_whole_scans_keep_the_camera_robot_on_the_truth() -> None:
    """The camera robot alone in the small house: it stands still for a whole scan at its
    start, and then every metre or so; the first one gives the square walls their reference;
    its pose stays closer to the truth than without whole scans."""
    truth: dict[tuple[str, int], np.ndarray] = {}
    core, worst = run({"r1": "depth"}, 120.0, true_poses=truth)
    slam = core.fleet.robots["r1"].slam
    camera = slam.sensor
    assert isinstance(camera, NarrowSensor)
    assert slam.stats.sweeps >= 10 and camera.ties.reference is not None
    assert camera.ties.reference[0] == 0
    # the robot did not move before its first whole scan
    first = camera.wholes[0]
    stamps = sorted(s for r, s in truth if r == "r1")
    before = [s for s in stamps if s <= slam.keyframes[first].stamp_ns]
    moved = between(truth["r1", before[0]], truth["r1", before[-1]])
    assert math.hypot(*moved[:2]) < 0.005 and len(before) > 20
    # each whole scan's match against the one before says how far the robot went
    index = {slam.trajectory.key(kf.index): kf for kf in slam.keyframes}
    err = []
    for rec in slam.trajectory.records("sweep"):
        ka, kb = rec.factor.keys()
        a, b = index[ka], index[kb]
        true_rel = between(truth["r1", a.stamp_ns], truth["r1", b.stamp_ns])
        m = rec.factor.measured()
        err.append(math.hypot(m.x() - true_rel[0], m.y() - true_rel[1]))
    assert len(err) >= 8 and np.median(err) < 0.03, err
    _, without = run({"r1": "depth"}, 120.0, {"sweep": {"enabled": False}})
    assert worst["r1"] < 0.2 and without["r1"] > worst["r1"] + 0.05, (worst, without)


def test_a_camera_robot_pickled_mid_run_goes_on_as_the_original() -> None:
    """A snapshot pickles each robot's SLAM with its sensor models: the copy, fed the same
    scans, gives the same poses, with its own sweep and square walls (not the original's)."""
    import pickle

    core, _ = run({"r1": "depth"}, 3.0)
    slam = core.fleet.robots["r1"].slam
    copy = pickle.loads(pickle.dumps(slam))
    assert isinstance(copy.sensor, NarrowSensor) and copy.narrow
    assert copy.sensor.sweep is not slam.sensor.sweep
    a = np.linspace(-FOV / 2, FOV / 2, 60)
    assert slam._last_stamp_ns is not None and slam._last_odom is not None
    for i in range(1, 31):
        stamp = slam._last_stamp_ns + 100_000_000
        odom = slam._last_odom + np.array([0.0, 0.0, 0.1])   # turning on the spot
        ranges = 2.0 / np.cos(a) + 0.001 * i
        assert np.allclose(slam.add_scan(stamp, odom, ranges, a),
                           copy.add_scan(stamp, odom, ranges, a), rtol=0, atol=1e-9)
        assert slam.sweep_due(stamp) == copy.sweep_due(stamp)
    # (the graph is solved again from its factors when unpickled: equal to rounding)
    assert len(copy.keyframes) == len(slam.keyframes) > 2
    assert np.allclose(slam.keyframe_poses(), copy.keyframe_poses(), rtol=0, atol=1e-9)
