"""Wheel odometry drifts as its noise model says, and robots obey limits and collisions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import wrap_angle
from sim.odometry import OdometryNoise, integrate
from sim.robot import DriveLimits, arc_step, limit_command
from sim.simulator import SimParams, Simulator
from sim.world import World

NOISE = OdometryNoise(alpha1=4e-3, alpha2=1e-3, alpha3=1e-3, alpha4=1e-4, scale_sigma=0.0,
                      turn_scale_sigma=0.0)


def square_commands(side_m: float, v: float, w: float, dt: float) -> list[tuple[float, float]]:
    """Open-loop (v, ω) per step for a square: drive a side, turn 90°, four times."""
    cmds = []
    for _ in range(4):
        cmds += [(v, 0.0)] * round(side_m / v / dt) + [(0.0, 0.0)] * 5
        cmds += [(0.0, w)] * round(math.pi / 2 / w / dt) + [(0.0, 0.0)] * 5
    return cmds


def predicted_covariance(increments: list[tuple[float, float, float]],
                         noise: OdometryNoise) -> np.ndarray:
    """Linearised propagation of the odometry error (x, y, θ) along the true path:
    Σ ← F Σ Fᵀ + G Q Gᵀ with F, G the Jacobians of the arc update w.r.t. pose and (Δs, Δθ)."""
    S = np.zeros((3, 3))
    for theta, ds, dth in increments:
        mid = theta + dth / 2
        F = np.array([[1, 0, -ds * math.sin(mid)], [0, 1, ds * math.cos(mid)], [0, 0, 1]])
        G = np.array([[math.cos(mid), -ds / 2 * math.sin(mid)],
                      [math.sin(mid), ds / 2 * math.cos(mid)], [0, 1]])
        S = F @ S @ F.T + G @ noise.covariance(ds, dth) @ G.T
    return S


def test_odometry_drift_over_a_driven_square_matches_the_noise_model() -> None:
    """300 robots drive the same square in the simulator; their odometry errors at the end
    must have the mean (zero) and covariance the configured α1–α4 predict."""
    n = 300
    spawn = {f"r{i + 1}": (4.0 * (i % 20), 4.0 * (i // 20), 0.0) for i in range(n)}
    far = World.from_shapes("empty", "test", [np.array([[500, 500], [501, 500], [501, 501],
                                                        [500, 501.0]])], [])
    params = SimParams(step_ns=100_000_000, substeps=1, odometry=NOISE)
    sim = Simulator(far, spawn, params, seed=42)
    dt = 0.1
    increments = []
    for v, w in square_commands(1.0, 0.5, 1.0, dt):
        for rid in spawn:
            sim.set_command(rid, v, w)
        theta = sim.robots["r1"].pose[2]
        sim.advance()
        r1 = sim.robots["r1"]
        increments.append((theta, r1.v * dt, r1.w * dt))
    truth = np.array([r.pose for r in sim.robots.values()])
    odom = np.array([r.odom for r in sim.robots.values()])
    assert np.allclose(truth[:, 2], truth[0, 2]) and sum(r.collisions for r in
                                                         sim.robots.values()) == 0
    err = odom - truth
    err[:, 2] = wrap_angle(err[:, 2])
    S = predicted_covariance(increments, NOISE)
    emp = np.cov(err.T)
    # variances within ±30 % (the estimate's own spread is ±8 % at n = 300)
    assert np.diag(emp) == pytest.approx(np.diag(S), rel=0.3)
    assert np.all(np.abs(err.mean(axis=0)) < 4 * np.sqrt(np.diag(S) / n))
    # Mahalanobis distances are χ²(3): mean 3
    d2 = np.einsum("ni,ij,nj->n", err, np.linalg.inv(S), err)
    assert d2.mean() == pytest.approx(3.0, abs=0.5)
    assert math.sqrt(S[0, 0] + S[1, 1]) > 0.02  # it does drift


def test_a_robot_standing_still_does_not_drift_and_biases_make_drift_systematic() -> None:
    rng = np.random.default_rng(0)
    noise = OdometryNoise()
    ds, dth = noise.measure(rng, np.zeros(10), np.zeros(10))
    assert np.all(ds == 0) and np.all(dth == 0)
    biased = OdometryNoise(alpha1=0, alpha2=0, alpha3=0, alpha4=0)
    ds, dth = biased.measure(rng, np.full(3, 1.0), np.full(3, 0.5), bias=(0.02, -0.01))
    assert np.allclose(ds, 1.02) and np.allclose(dth, 0.495)


def test_vectorised_and_scalar_arc_updates_agree() -> None:
    rng = np.random.default_rng(1)
    poses = rng.uniform(-3, 3, (50, 3))
    ds, dth = rng.uniform(-0.1, 0.1, 50), rng.uniform(-0.3, 0.3, 50)
    vec = integrate(poses, ds, dth)
    for p, a, b, out in zip(poses, ds, dth, vec, strict=True):
        assert np.allclose(arc_step(tuple(p), a, b, 1.0), out)


def test_velocity_limits_keep_curvature_and_bound_acceleration() -> None:
    lim = DriveLimits()
    v, w = limit_command(2.0, 1.0, 0.46, 0.23, lim, 0.02)  # near the target: only the limits
    assert abs(v) + abs(w) * lim.track_width_m / 2 == pytest.approx(lim.v_max_mps)
    assert v / w == pytest.approx(2.0)
    v, w = limit_command(0.5, 0.0, 0.0, 0.0, lim, 0.02)    # from rest: acceleration limit
    assert v == pytest.approx(lim.accel_max_mps2 * 0.02)


def test_collisions_stop_the_robot_and_are_counted_once() -> None:
    wall = World.from_shapes("wall", "test", [np.array([[1.0, -2], [1.2, -2], [1.2, 2],
                                                        [1.0, 2.0]])], [])
    sim = Simulator(wall, {"r1": (0.0, 0.0, 0.0)}, SimParams(), seed=0)
    for _ in range(40):
        sim.set_command("r1", 0.4, 0.0)
        sim.advance()
    r = sim.robots["r1"]
    assert r.collisions == 1 and r.in_contact and r.v == 0.0
    assert 1.0 - 0.13 - 0.02 < r.pose[0] < 1.0 - 0.13
    x_contact = r.pose[0]
    sim.set_command("r1", -0.3, 0.0)  # backing away works
    for _ in range(5):
        sim.advance()
    assert r.pose[0] < x_contact - 0.05 and not r.in_contact and r.collisions == 1
