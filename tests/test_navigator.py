"""Navigator: how often it looks at its target again, per explorer."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import ArrayLike

from server.control import Obstacles, PursuitParams, StuckDetector
from server.exploration import (
    Explorer,
    ExplorerParams,
    FrontierExplorer,
    MapAnalysis,
    VisitedTargets,
    VoronoiExplorer,
    navigator,
)
from server.exploration.navigator import EXPLORING, Navigator
from server.exploration.replan import Replan, Replanned, replan
from server.planning import OccupancyGrid
from tests.test_exploration_skeleton import t_corridor

START = np.array([3.0, 3.75, 0.0])   # in the corridor, both open ends ahead


class Counting:
    """Counts the map analyses an explorer makes (one per decision) and the replans to a kept
    target (each one analysis too)."""

    def __init__(self, explorer: Explorer) -> None:
        self.explorer = explorer
        self.analyses = 0
        real = explorer.analyse

        def analyse(grid: OccupancyGrid, include_xy: ArrayLike,
                    visited: VisitedTargets | None = None) -> MapAnalysis:
            self.analyses += 1
            return real(grid, include_xy, visited)

        explorer.analyse = analyse  # type: ignore[method-assign]

    def replan(self, job: Replan) -> Replanned:
        self.analyses += 1
        return replan(job)


def run(explorer: Explorer, times_s: list[float], replan_period_s: float = 4.0) -> list[int]:
    """Analyses made after each step at ``times_s`` (the robot stands still at START)."""
    counting = Counting(explorer)
    nav = Navigator(explorer, PursuitParams(), None, StuckDetector(), replan_period_s)
    grid, visited = t_corridor(), VisitedTargets()
    out = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(navigator, "replan", counting.replan)
        for t in times_s:
            nav.step(t, START, START, Obstacles(), lambda: grid, visited)
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


def test_a_replan_in_a_planner_process_gives_the_path_planned_in_line() -> None:
    """With a planner pool the replan runs in another process: the step that hands it over
    keeps the robot's path, a later step takes the answer, and it is the path planned here."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor

    grid, visited = t_corridor(), VisitedTargets()
    here = Navigator(VoronoiExplorer(ExplorerParams(lam=1.0)), PursuitParams(), None,
                     StuckDetector(), 1.0)
    away = Navigator(VoronoiExplorer(ExplorerParams(lam=1.0)), PursuitParams(), None,
                     StuckDetector(), 1.0)
    pose = START + np.array([0.3, 0.0, 0.0])
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        for nav in (here, away):
            nav.step(0.0, START, START, Obstacles(), lambda: grid, visited)
        assert here.target_xy == away.target_xy and here.path_xy is not None
        first = away.path_xy
        here.step(1.0, pose, START, Obstacles(), lambda: grid, visited)
        away.step(1.0, pose, START, Obstacles(), lambda: grid, visited, planner=pool)
        assert away._replanning is not None and away.path_xy is first   # handed over
        deadline = time.monotonic() + 30
        while not away._replanning.done() and time.monotonic() < deadline:
            time.sleep(0.05)
        away.step(1.1, pose, START, Obstacles(), lambda: grid, visited, planner=pool)
    assert away._replanning is None and away.path_xy is not first
    assert here.path_xy is not None and away.path_xy is not None
    assert np.allclose(away.path_xy, here.path_xy)


def test_a_robot_alone_stands_while_a_planner_process_decides_for_it() -> None:
    """A decision handed to the pool: the robot gets STOP until it comes back, then follows
    the target and path that deciding here gives."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor

    grid = t_corridor()
    here = Navigator(VoronoiExplorer(ExplorerParams(lam=1.0)), PursuitParams(), None,
                     StuckDetector(), 1.0)
    away = Navigator(VoronoiExplorer(ExplorerParams(lam=1.0)), PursuitParams(), None,
                     StuckDetector(), 1.0)
    here.step(0.0, START, START, Obstacles(), lambda: grid, VisitedTargets())
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        twist = away.step(0.0, START, START, Obstacles(), lambda: grid, VisitedTargets(),
                          planner=pool)
        assert twist.v_mps == 0.0 and twist.omega_rps == 0.0 and away._deciding is not None
        deadline = time.monotonic() + 30
        while not away._deciding.done() and time.monotonic() < deadline:
            time.sleep(0.05)
        twist = away.step(0.1, START, START, Obstacles(), lambda: grid, VisitedTargets(),
                          planner=pool)
    assert away._deciding is None and away.mode == EXPLORING
    assert away.target_xy == here.target_xy and away.stats.decisions == 1
    assert len(away.own_explorer.walls_seen) == len(here.own_explorer.walls_seen) > 0
    assert twist.v_mps != 0.0 or twist.omega_rps != 0.0
