"""Navigator: how often it looks at its target again, per explorer."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import ArrayLike

from server.control import PursuitParams, StuckDetector
from server.exploration import (
    Explorer,
    ExplorerParams,
    FrontierExplorer,
    MapAnalysis,
    VisitedTargets,
    VoronoiExplorer,
)
from server.navigator import EXPLORING, Navigator
from server.planning import OccupancyGrid
from tests.test_exploration_skeleton import t_corridor

START = np.array([3.0, 3.75, 0.0])   # in the corridor, both open ends ahead


class Counting:
    """Counts the map analyses an explorer makes (one per decision or target check)."""

    def __init__(self, explorer: Explorer) -> None:
        self.explorer = explorer
        self.analyses = 0
        real = explorer.analyse

        def analyse(grid: OccupancyGrid, include_xy: ArrayLike,
                    visited: VisitedTargets | None = None) -> MapAnalysis:
            self.analyses += 1
            return real(grid, include_xy, visited)

        explorer.analyse = analyse  # type: ignore[method-assign]


def run(explorer: Explorer, times_s: list[float], replan_period_s: float = 4.0) -> list[int]:
    """Analyses made after each step at ``times_s`` (the robot stands still at START)."""
    counting = Counting(explorer)
    nav = Navigator(explorer, PursuitParams(), None, StuckDetector(), replan_period_s)
    grid, visited = t_corridor(), VisitedTargets()
    out = []
    for t in times_s:
        nav.step(t, START, START, np.zeros((0, 2)), lambda: grid, visited)
        assert nav.mode == EXPLORING and nav.target_xy is not None
        out.append(counting.analyses)
    return out


def test_voronoi_targets_are_looked_at_every_recheck_period() -> None:
    ex = VoronoiExplorer(ExplorerParams(lam=1.0, recheck_period_s=1.0))
    assert ex.recheck_period_s == 1.0
    # decision at 0 s; nothing at 0.5 s; a look at the target at 1.0 s and again at 2.0 s
    assert run(ex, [0.0, 0.5, 1.0, 1.5, 2.0]) == [1, 1, 2, 2, 3]


def test_the_navigators_period_bounds_the_explorers() -> None:
    ex = VoronoiExplorer(ExplorerParams(lam=1.0, recheck_period_s=10.0))
    assert run(ex, [0.0, 2.0, 3.0], replan_period_s=3.0) == [1, 1, 2]


@pytest.mark.parametrize("replan_period_s", [2.0, 4.0])
def test_frontier_baseline_keeps_the_navigators_period(replan_period_s: float) -> None:
    ex = FrontierExplorer(ExplorerParams())
    assert ex.recheck_period_s is None
    steps = [0.0, 1.0, replan_period_s - 0.1, replan_period_s]
    assert run(ex, steps, replan_period_s) == [1, 1, 1, 2]
