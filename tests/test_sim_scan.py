"""LIDAR: scans against analytic distances, other robots, no-returns, brute-force agreement."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas import ranges_from_mm
from sim.loader import load_world
from sim.process import step_messages
from sim.raycast import RayCaster, line_of_sight
from sim.simulator import SimParams, Simulator
from sim.world import World
from tests.conftest import DATA

ROOM = (-2.0, -1.5, 4.0, 3.0)  # inner walls x0, y0, x1, y1 [m]


def room(thick: float = 0.15) -> World:
    x0, y0, x1, y1 = ROOM

    def box(ax: float, ay: float, bx: float, by: float) -> np.ndarray:
        return np.array([[ax, ay], [bx, ay], [bx, by], [ax, by]])

    return World.from_shapes("room", "test", [
        box(x0 - thick, y0 - thick, x1 + thick, y0), box(x0 - thick, y1, x1 + thick, y1 + thick),
        box(x0 - thick, y0, x0, y1), box(x1, y0, x1 + thick, y1)], [])


def analytic(pose: tuple[float, float, float], angles: np.ndarray) -> np.ndarray:
    """Distance from ``pose`` to the inner walls of ROOM along each beam."""
    x0, y0, x1, y1 = ROOM
    x, y, th = pose
    a = th + angles
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (x1 - x) / c, np.where(c < 0, (x0 - x) / c, np.inf))
        ty = np.where(s > 0, (y1 - y) / s, np.where(s < 0, (y0 - y) / s, np.inf))
    return np.minimum(tx, ty)


def test_scan_in_a_known_room_matches_analytic_distances_within_3_sigma() -> None:
    pose = (0.7, 0.4, 0.6)
    sim = Simulator(room(), {"r1": pose}, SimParams(), seed=3)
    lid = sim.p.lidar
    errors = []
    for _ in range(5):  # five sweeps from the same pose: fresh noise, same truth
        msgs, _ = step_messages(sim, sim.sense(), "room")
        (sweep,) = [m for k, m in msgs if k.endswith("/lidar")]
        r = ranges_from_mm(sweep.ranges_mm)
        truth = analytic(pose, sweep.angles_rad())
        assert sweep.n_beams == 400 and np.all(np.isfinite(r))
        errors.append(r - truth)
        sim.advance()
    e = np.concatenate(errors)
    sigma = math.hypot(lid.sigma_m, 0.001 / math.sqrt(12))  # noise and mm quantisation
    assert np.mean(np.abs(e) <= 3 * sigma) > 0.99         # 99.7 % expected inside 3σ
    assert np.max(np.abs(e)) < 5 * sigma
    assert abs(e.mean()) < 4 * sigma / math.sqrt(len(e))   # unbiased
    assert e.std() == pytest.approx(sigma, rel=0.1)        # the configured noise, no more


def test_other_robots_appear_and_far_beams_are_no_returns() -> None:
    world = World.from_shapes("far", "test", [np.array([[20, -1], [21, -1], [21, 1], [20, 1.0]])],
                              [])
    sim = Simulator(world, {"r1": (0.0, 0.0, 0.0), "r2": (2.0, 0.0, 1.0)}, SimParams(), seed=0)
    obs = sim.sense()
    r = obs.ranges_m["r1"]
    ahead = 200  # beam at angle 0 (angle_min = -pi, 400 beams)
    assert r[ahead] == pytest.approx(2.0 - sim.p.drive.radius_m, abs=0.04)
    assert np.isinf(r[0]) and np.isinf(r[100])             # nothing within 10 m behind/aside
    msgs, _ = step_messages(sim, obs, "far")
    sweep = next(m for k, m in msgs if k.endswith("r1/lidar"))
    assert np.frombuffer(sweep.ranges_mm, "<u2")[0] == 0   # no-return on the wire
    assert sweep.range_max_mm == 10000 and sweep.range_min_mm == 50


def brute_force(pose: np.ndarray, angles: np.ndarray, seg: np.ndarray,
                max_range: float) -> np.ndarray:
    out = np.full(len(angles), np.inf)
    for i, a in enumerate(angles + pose[2]):
        d = np.array([math.cos(a), math.sin(a)])
        for s in seg:
            p, e = s[:2] - pose[:2], s[2:] - s[:2]
            den = d[0] * e[1] - d[1] * e[0]
            if abs(den) < 1e-14:
                continue
            t = (p[0] * e[1] - p[1] * e[0]) / den
            u = (p[0] * d[1] - p[1] * d[0]) / den
            if t > 0 and 0 <= u <= 1:
                out[i] = min(out[i], t)
    out[out > max_range] = np.inf
    return out


def test_vectorised_casting_agrees_with_brute_force_in_the_large_world() -> None:
    world = load_world(DATA / "worlds" / "thesis" / "house_large.world")
    caster = RayCaster(world.segments)
    rng = np.random.default_rng(11)
    n = 90
    angles = -math.pi + 2 * math.pi / n * np.arange(n)
    for _ in range(4):
        pose = (rng.uniform(-24, 24), rng.uniform(-24, 24), rng.uniform(-3, 3))
        fast = caster.cast(pose, n, -math.pi, 2 * math.pi / n, 10.0)
        slow = brute_force(np.array(pose), angles, world.segments, 10.0)
        assert np.array_equal(np.isfinite(fast), np.isfinite(slow))
        fin = np.isfinite(fast)
        assert np.allclose(fast[fin], slow[fin], atol=1e-9)


def test_line_of_sight() -> None:
    seg = np.array([[0.0, -1.0, 0.0, 1.0]])
    assert not line_of_sight((-1.0, 0.0), (1.0, 0.0), seg)
    assert line_of_sight((-1.0, 2.0), (1.0, 2.0), seg)
    assert not line_of_sight((-1.0, 2.0), (1.0, 2.0), seg, np.array([[0.0, 2.0, 0.1]]))
