"""A changing building on a known map (``server/knownmap/changes``, extend mode): a closed door
shown closed after one pass, the map's views it contradicts retired, and map keyframes seen
again retired so that the map does not grow from mission to mission.

The map is surveyed from the truth of the small house (``bench.support.survey``); the
missions run in ``small_house.changed`` (two doors closed, three boxes brought in)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.support.known_mission import WORLDS, KnownMission, demo_config, mission
from bench.support.survey import survey_map
from server.command.operator import OperatorCommand
from server.knownmap.mapdata import KnownMap
from server.slam.mapping import render_grid
from sim.floorplan import SMALL_HOUSE_CLOSED

HOUSE = WORLDS / "small_house.world"
CHANGED = WORLDS / "small_house.changed.world"


@pytest.fixture(scope="module")
def house() -> KnownMap:
    return survey_map(HOUSE)


def _occupied(m: KnownMission, known: KnownMap, x: float, y: float) -> tuple[float, bool]:
    """The map's log-odds at (x, y), the most of a 0.2 m square, and whether it is known."""
    grid = render_grid(m.core.fleet.stages.mapper().params, known.keyframes, known.poses)
    ix, iy = grid.cell_of(np.array([[x, y]]))[0]
    rows, cols = slice(max(iy - 1, 0), iy + 2), slice(max(ix - 1, 0), ix + 2)
    return float(grid.log_odds[rows, cols].max()), bool(grid.observed[rows, cols].any())


def _drive(m: KnownMission, xy: tuple[float, float], s: float) -> None:
    m.core.operate(OperatorCommand("goto", "r1", xy), int(m.sim_time_s * 1e9))
    m.run_until(m.sim_time_s + s)


@pytest.mark.slow
def test_a_closed_door_is_shown_closed_after_one_pass(house: KnownMap) -> None:
    door = SMALL_HOUSE_CLOSED[0]                 # the north-west room's door from the hall
    m = mission(CHANGED, house, {"r1": np.array([-8.5, 2.2, 0.0])},
                demo_config("small-house-3", mode="extend"), np.zeros(3))
    before, known_before = _occupied(m, house, *door)
    assert known_before and before < 0, "the map shows the door open"
    m.run_until(15.0, lambda m: bool(m.placed))
    assert m.placed and m.placed[0].error_m <= 0.10
    _drive(m, (-5.0, 2.2), 20.0)                 # along the hall, past the door
    assert m.core.known is not None and m.core.known.upkeep is not None
    changed = [e for e in m.core.events.all if e.kind == "map_changed"]
    assert changed, m.core.known.summary()
    f = [e.figures or {} for e in changed]
    assert any(g["x0"] - 0.6 <= door[0] <= g["x1"] + 0.6 and
               g["y0"] - 0.6 <= door[1] <= g["y1"] + 0.6 for g in f), f
    left = m.core.known.mission_map()
    assert left is not None
    after, _ = _occupied(m, left, *door)
    assert after > 0, "the map left shows the door closed"
    counts = m.core.known.upkeep.counts
    assert counts["trimmed"] >= 1 and counts["superseded"] >= 1
    # what it retired is out of the map left: it holds fewer of the survey's keyframes
    assert sum(s == "survey" for s in left.sources) <= len(house) - counts["superseded"]


@pytest.mark.slow
def test_missions_in_a_row_on_the_same_path_do_not_grow_the_map(house: KnownMap) -> None:
    known, sizes = house, []
    for k in range(2):
        m = mission(HOUSE, known, {"r1": np.array([-8.5, 2.2, 0.0])},
                    demo_config("small-house-3", mode="extend"), np.zeros(3), seed=k)
        m.run_until(15.0, lambda m: bool(m.placed))
        assert m.placed
        _drive(m, (6.0, 2.2), 40.0)              # along the hall, the same way each time
        assert m.core.known is not None
        left = m.core.known.mission_map()
        assert left is not None
        sizes.append(len(left))
        known = left
    added = sizes[0] - len(house)
    assert added > 0, "the first mission mapped its own keyframes in"
    # the second mission's keyframes replace the first's where it passed again
    assert sizes[1] - sizes[0] <= 0.5 * added, (len(house), sizes)
