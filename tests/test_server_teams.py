"""Merge verification on sightings built from known geometry: consistent sightings (even with
useless tag yaw) give the transform between two teams' frames; false ones do not merge."""

from __future__ import annotations

import math

import numpy as np

from factors.rendezvous import Sighting
from schemas.se2 import between, compose, inverse, wrap_angle
from server.rendezvous.evidence import MergeVerifier, VerifierParams, make_record, rigid_fit

T_XY = np.array([3.0, -2.0, 0.8])   # team Y's frame in team X's
SIG = (0.03, 0.03, math.radians(0.5))


def sighting(P_obs: np.ndarray, P_seen: np.ndarray, rng: np.random.Generator,
             yaw_sigma: float = 1.2) -> Sighting:
    rel = between(P_obs, P_seen)
    r = math.hypot(rel[0], rel[1])
    return Sighting(r + rng.normal() * 0.02, math.atan2(rel[1], rel[0]) + rng.normal() * 0.005,
                    rel[2] + rng.normal() * yaw_sigma, 0.03, 0.008, yaw_sigma)


def feed(v: MergeVerifier, n: int, rng: np.random.Generator, wrong: bool = False,
         reverse: bool = False) -> list[object]:
    """Robot a (team X) sees robot b (team Y) while b drives a line; ``reverse``: b sees a
    while a drives (the robot seen must move for positions alone to fix the rotation)."""
    out = []
    for i in range(n):
        a_in_X = np.array([0.0, 0.0, 0.1]) if not reverse else np.array([0.0, 0.5 * i, 0.1])
        b_in_Y = np.array([0.5 * i, 1.0, -0.3 + 0.05 * i]) if not reverse else \
            np.array([1.0, 1.0, -0.3])
        b_in_X = compose(T_XY, b_in_Y)
        if wrong:  # another robot's tag: the robot seen is not where b is
            b_in_X = compose(b_in_X, [1.5, 0.5, 0.7])
        if not reverse:
            s = sighting(a_in_X, b_in_X, rng)
            rec = make_record(i * 10**9, "a", "b", s, (0, np.zeros(3)), (0, np.zeros(3)),
                              a_in_X, b_in_Y, SIG)
            out.append(v.add("X", "Y", rec))
        else:
            a_in_Y = compose(inverse(T_XY), a_in_X)
            s = sighting(b_in_Y, a_in_Y, rng)
            rec = make_record(i * 10**9, "b", "a", s, (0, np.zeros(3)), (0, np.zeros(3)),
                              b_in_Y, a_in_X, SIG)
            out.append(v.add("Y", "X", rec))
    return out


def test_rigid_fit_recovers_a_transform() -> None:
    rng = np.random.default_rng(0)
    src = rng.normal(size=(6, 2)) * 3
    T = np.array([1.0, 2.0, -2.5])
    c, s = math.cos(T[2]), math.sin(T[2])
    dst = src @ np.array([[c, s], [-s, c]]) + T[:2]
    np.testing.assert_allclose(rigid_fit(src, dst, np.ones(6)), T, atol=1e-9)


def test_positions_alone_give_the_transform_once_the_robot_moved() -> None:
    v = MergeVerifier(VerifierParams())
    props = feed(v, 10, np.random.default_rng(1))
    assert props[0] is None and props[1] is None   # one place, useless yaw: not yet
    # three places a metre apart agree, but leave the rotation a few degrees uncertain
    assert props[2] is None
    got = next(p for p in props if p is not None)
    assert math.sqrt(got.cov_ab[2, 2]) <= math.radians(1.0)
    assert got.team_a == "X" and got.team_b == "Y"
    assert math.hypot(*(got.T_ab[:2] - T_XY[:2])) < 0.05
    assert abs(wrap_angle(got.T_ab[2] - T_XY[2])) < math.radians(1.5)


def test_sightings_from_the_other_side_agree() -> None:
    v = MergeVerifier(VerifierParams())
    got = [p for p in feed(v, 10, np.random.default_rng(2), reverse=True) if p is not None]
    assert got and math.hypot(*(got[-1].T_ab[:2] - T_XY[:2])) < 0.05


def test_false_sightings_scattered_in_do_not_pass() -> None:
    rng = np.random.default_rng(3)
    v = MergeVerifier(VerifierParams())
    assert all(p is None for p in feed(v, 2, rng, wrong=True))
    # random false sightings: never three consistent ones
    for i in range(12):
        P = np.array([0.0, 0.0, 0.0])
        s = Sighting(rng.uniform(1, 5), rng.uniform(-0.5, 0.5), rng.uniform(-3, 3), 0.03, 0.008,
                     1.2)
        rec = make_record(i * 10**9, "a", "b", s, (0, np.zeros(3)), (0, np.zeros(3)), P,
                          np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), 0.0]), SIG)
        assert v.add("X", "Y", rec) is None


def _grid(free: np.ndarray, occ: np.ndarray) -> object:
    from server.slam.grid import GridParams, OccupancyGrid

    log_odds = np.where(occ, 3.0, np.where(free, -1.9, 0.0))
    return OccupancyGrid.from_dense(GridParams(resolution_m=0.05), (0.0, 0.0), log_odds,
                                    free | occ)


def test_map_check_ignores_grazed_walls_but_not_walls_in_a_room() -> None:
    from server.rendezvous.maps import map_agreement

    h = w = 80
    room = np.zeros((h, w), dtype=bool)
    room[10:70, 10:70] = True                      # a 3 × 3 m room, seen free
    wall = np.zeros((h, w), dtype=bool)
    wall[40, 10:70] = True                         # b saw a wall across it
    b_free = room & ~wall
    b_free[41:70] = False                          # ... and nothing behind the wall
    b = _grid(b_free, wall)
    # a saw the same room, its side of the wall erased by grazing beams: the free cells there
    # border what a never saw beyond the wall
    a_free = room.copy()
    a_free[42:70] = False
    a_occ = np.zeros((h, w), dtype=bool)
    a_occ[40, 10:30] = True                        # only part of the wall kept
    a_free &= ~a_occ
    a = _grid(a_free, a_occ)
    same = map_agreement(a, b, np.zeros(3))
    assert same.conflicts == 0
    # a wrong transform puts b's wall in the middle of a room a saw free all around
    open_room = _grid(room, np.zeros((h, w), dtype=bool))
    wrong = map_agreement(open_room, b, np.array([0.0, -0.5, 0.0]))
    assert wrong.conflicts >= 40 and wrong.conflict_ratio > 0.5
