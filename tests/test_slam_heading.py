"""Square walls hold a narrow sensor's heading: the wall direction of a keyframe, the rule's
check before use, the ties it makes, and those ties against the truth in the small house."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import between, wrap_angle
from server.slam.heading import SquareWalls, wall_direction, wrap_quarter
from tests.test_slam_narrow import run

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow


def normals_at(angles_rad: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=1)


def test_a_keyframes_wall_direction_is_its_normals_fourfold_mean() -> None:
    rng = np.random.default_rng(0)
    # two walls at right angles, turned by 17°, normals 1° noisy: both faces and sides count
    a = math.radians(17.0) + rng.integers(0, 4, 200) * math.pi / 2 + rng.normal(0, 0.017, 200)
    found = wall_direction(normals_at(a), 20)
    assert found is not None
    assert math.degrees(found[0]) == pytest.approx(17.0, abs=0.3) and found[1] > 0.95
    # normals every which way: no direction to speak of
    spread = wall_direction(normals_at(rng.uniform(-math.pi, math.pi, 200)), 20)
    assert spread is not None and spread[1] < 0.2
    # too few, and NaN normals (no line fitted) are not counted
    few = normals_at(np.zeros(30))
    few[12:] = np.nan
    assert wall_direction(few, 20) is None
    assert wrap_quarter(math.radians(50)) == pytest.approx(math.radians(-40))


def keyframe_walls(psi: float, theta: float, rng: np.random.Generator,
                   turns: tuple[float, ...] = (0.0, math.pi / 2)) -> np.ndarray:
    """Normals a robot at heading ``theta`` sees, in its own frame, of walls at ``psi`` plus
    each of ``turns`` (map frame)."""
    a = psi + rng.choice(turns, 40) - theta + rng.normal(0, 0.01, 40)
    return normals_at(a)


def test_square_walls_tie_drifted_headings_back_to_the_truth() -> None:
    rng = np.random.default_rng(1)
    psi = math.radians(23.0)                   # the building, turned in the map frame
    sq = SquareWalls(min_checked=5, partners=3)
    truth: dict[int, float] = {}
    drift: dict[int, float] = {}               # the estimate drifts 10° over the run
    ties = []
    for k in range(40):
        truth[k] = rng.uniform(-math.pi, math.pi)
        drift[k] = math.radians(0.25) * k

        def rel(j: int, k: int = k) -> float:
            return wrap_angle(truth[k] + drift[k] - truth[j] - drift[j])

        got = sq.observe(k, keyframe_walls(psi, truth[k], rng), rel)
        ties += [(j, k, h) for j, h in got]
    assert sq.holds and sq.checked == 5
    assert len({k for _, k, _ in ties}) >= 30 and min(k for _, k, _ in ties) == 6
    partners = {j for j, _, _ in ties}
    assert 0 in partners and len(partners) >= 4          # the first, and others spread out
    # what each tie says is the true relative heading, not the drifted estimate's
    err = [math.degrees(wrap_angle(h - (truth[k] - truth[j]))) for j, k, h in ties]
    assert max(abs(e) for e in err) < 1.5, err
    # no tie where the estimate drifted further than a keyframe may be corrected by
    assert all(math.degrees(drift[k] - drift[j]) <= 8.5 for j, k, _ in ties)
    assert max(k for j, k, _ in ties if j == 0) <= 34


def test_walls_that_are_not_square_never_tie_anything() -> None:
    rng = np.random.default_rng(2)
    sq = SquareWalls(min_checked=10)
    hexagon = (0.0, math.pi / 3, 2 * math.pi / 3)   # each view sees one wall of a hexagon
    for k in range(60):
        theta = rng.uniform(-math.pi, math.pi)
        walls = keyframe_walls(0.3, theta, rng, (float(rng.choice(hexagon)),))
        assert sq.observe(k, walls, lambda j, theta=theta: theta) == []
    assert sq.checked >= 10 and not sq.holds


def test_a_wall_off_the_square_grid_is_not_tied() -> None:
    rng = np.random.default_rng(3)
    sq = SquareWalls(min_checked=3, max_correction_deg=8.0)
    for k in range(5):
        sq.observe(k, keyframe_walls(0.0, 0.0, rng), lambda j: 0.0)
    assert sq.holds
    assert sq.observe(5, keyframe_walls(math.radians(20), 0.0, rng), lambda j: 0.0) == []
    tied = sq.observe(6, keyframe_walls(math.radians(4), 0.0, rng), lambda j: 0.0)
    assert tied and all(math.degrees(h) == pytest.approx(-4.0, abs=0.5) for _, h in tied)


def test_the_depth_robots_ties_in_the_small_house_agree_with_the_truth() -> None:
    """The camera robot alone: its keyframes are tied, and what each tie says of the relative
    heading of its two keyframes is what the simulator's truth says."""
    truth: dict[tuple[str, int], np.ndarray] = {}
    core, _ = run({"r1": "depth"}, 60.0, true_poses=truth)
    slam = core.fleet.robots["r1"].slam
    ties = slam.trajectory.records("heading")
    assert slam.stats.heading_ties >= 10 and len(ties) >= 20
    index = {slam.trajectory.key(kf.index): kf for kf in slam.keyframes}
    err = []
    for rec in ties:
        ka, kb = rec.factor.keys()
        a, b = index[ka], index[kb]
        true_rel = between(truth["r1", a.stamp_ns], truth["r1", b.stamp_ns])[2]
        err.append(math.degrees(wrap_angle(rec.factor.measured().theta() - true_rel)))
    assert np.median(np.abs(err)) < 1.0 and np.mean(err) == pytest.approx(0.0, abs=1.0), err
    # turned off, or for a LIDAR robot (narrow sensors only, by default): no ties
    core, _ = run({"r1": "depth"}, 20.0, {"square_walls": {"enabled": False}})
    assert not core.fleet.robots["r1"].slam.trajectory.records("heading")
    core, _ = run({"r1": "lidar"}, 20.0)
    assert not core.fleet.robots["r1"].slam.trajectory.records("heading")
