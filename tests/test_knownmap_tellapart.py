"""Telling placements apart (``server.knownmap.tellapart``): where a searching robot is sent
when its map fits two places alike, and when what it has seen tells them apart — on a
corridor that looks the same turned by half a turn but for a pillar."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from server.knownmap import tellapart
from server.knownmap.placing import Placement
from server.rendezvous.mapmatch import Layers, layers
from server.slam.grid import GridParams, OccupancyGrid

RES = 0.05
HALF_X, HALF_Y = 10.0, 2.0          # a corridor 20 × 4 m about the origin
PILLAR = (3.0, 1.0, 0.3)            # x, y, half side: breaks the half-turn symmetry
TURNED = np.array([0.0, 0.0, math.pi])


def _grid(seen_x: tuple[float, float]) -> OccupancyGrid:
    """The corridor as a map that has seen ``seen_x`` of it (its walls and floor)."""
    o = -HALF_X - 1.0, -HALF_Y - 1.0
    w, h = int((2 * HALF_X + 2) / RES), int((2 * HALF_Y + 2) / RES)
    x = o[0] + (np.arange(w) + 0.5) * RES
    y = o[1] + (np.arange(h) + 0.5) * RES
    X, Y = np.meshgrid(x, y)
    inside = (abs(X) <= HALF_X) & (abs(Y) <= HALF_Y)
    wall = inside & ((abs(X) >= HALF_X - 0.1) | (abs(Y) >= HALF_Y - 0.1))
    px, py, s = PILLAR
    wall |= (abs(X - px) <= s) & (abs(Y - py) <= s)
    seen = inside & (seen_x[0] <= X) & (seen_x[1] >= X)
    lo = np.where(wall, 3.0, -3.0)
    return OccupancyGrid.from_dense(GridParams(resolution_m=RES), o, lo, seen)


def _layers(seen_x: tuple[float, float]) -> tuple[Layers, NDArray[np.bool_]]:
    lay = layers(_grid(seen_x), tellapart.CELL_M)
    return lay, tellapart.clear_layer(lay)


def _known() -> tuple[Layers, NDArray[np.bool_]]:
    return _layers((-HALF_X, HALF_X))


def _own(seen_x: tuple[float, float]) -> tuple[Layers, NDArray[np.bool_]]:
    return _layers(seen_x)          # the robot stands in the real corridor


def test_the_robot_is_sent_toward_where_two_alike_placements_differ() -> None:
    known, kc = _known()
    own, oc = _own((-HALF_X, -4.0))          # its west end seen, not the pillar
    pose = np.array([-8.0, 0.0, 0.0])
    goal = tellapart.errand_goal(known, kc, own, oc, [np.zeros(3), TURNED], pose)
    assert goal is not None
    # toward the pillar (east), within what the robot knows, clear of its walls
    assert -8.0 + tellapart.NEAR_M <= goal[0] <= -4.0, goal
    assert abs(goal[1]) <= HALF_Y - tellapart.GOAL_CLEAR_M + 0.15, goal
    # the same placement twice, or one alone: nothing to tell apart, the robot explores
    assert tellapart.errand_goal(known, kc, own, oc, [np.zeros(3), np.zeros(3)], pose) is None
    assert tellapart.errand_goal(known, kc, own, oc, [np.zeros(3)], pose) is None


def test_alike_placements_are_told_apart_only_once_the_difference_is_seen() -> None:
    known, kc = _known()
    right = Placement(np.zeros(3), (), 100.0, 0.95)
    wrong = Placement(TURNED, (), 99.0, 0.95)
    own, oc = _own((-HALF_X, -4.0))          # the pillar not seen: both fit alike
    c_right = tellapart.conflicts(right.T_map_own, own, oc, known, kc)
    c_wrong = tellapart.conflicts(wrong.T_map_own, own, oc, known, kc)
    assert not tellapart.apart(c_right, c_wrong), (c_right, c_wrong)
    assert tellapart.told_apart([right, wrong], 0.8, own, oc, known, kc) is None
    own, oc = _own((-HALF_X, HALF_X))        # all of it seen, the pillar too
    c_right = tellapart.conflicts(right.T_map_own, own, oc, known, kc)
    c_wrong = tellapart.conflicts(wrong.T_map_own, own, oc, known, kc)
    assert c_right <= 2 and tellapart.apart(c_right, c_wrong), (c_right, c_wrong)
    assert tellapart.told_apart([wrong, right], 0.8, own, oc, known, kc) is right
    # a placement far weaker is no tie: the ordinary clear winner decides, not this rule
    assert tellapart.told_apart([right, Placement(TURNED, (), 10.0, 0.9)], 0.8, own, oc,
                                known, kc) is None


@pytest.mark.slow
def test_in_the_ambiguous_wings_a_robot_is_sent_to_tell_them_apart_and_placed_right() -> None:
    """Closed loop, the real simulator and core: a robot in the mirror-image wings (seed 1:
    its corridor fits both wings' and their other corridors) is sent where its placements
    differ and placed, right, well within the 120 s it was not placed in before."""
    from bench.support.known_mission import WORLDS, demo_config, free_poses, mission
    from bench.support.survey import survey_map

    world = WORLDS / "ambiguous_wings.world"
    m = mission(world, survey_map(world), {"r1": free_poses(world, 1,
                                                            np.random.default_rng(1))[0]},
                demo_config("ambiguous-2"), np.zeros(3), seed=1)
    m.run_until(60.0, lambda m: bool(m.placed))
    assert m.core.known is not None
    assert m.core.known.counts["tell_apart"] >= 1
    assert m.placed and not m.wrong(), (m.placed, m.wrong())
    assert m.placed[0].error_m <= 0.10


def test_the_way_is_counted_in_steps_around_walls() -> None:
    open_ = np.ones((5, 7), bool)
    open_[:4, 3] = False                    # a wall with a gap at the bottom row
    d = tellapart._wavefront(open_, (0, 0))
    assert d[0, 2] == 2 and d[4, 3] == 4    # diagonal steps count one
    assert d[0, 4] == 8                     # around the wall, not through it
    assert d[1, 3] == -1                    # the wall itself is never reached
