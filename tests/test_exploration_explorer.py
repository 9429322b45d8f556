"""Exploration decisions, termination, coverage and multi-robot assignment."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest

from server.exploration import (
    AnalysisParams,
    Decision,
    ExplorerParams,
    Finished,
    FrontierExplorer,
    VisitedTargets,
    VoronoiExplorer,
    assign_optimal,
    assign_separated,
    coverage,
    explored_area_m2,
    make_explorer,
)
from server.planning import OccupancyGrid, StartOccupied
from tests.test_exploration_skeleton import t_corridor

LEFT_START = (3.0, 3.75, 0.0)   # corridor, nearer to the left open end
STEM = (6.25, 1.0, 0.0)         # bottom of the dead-end stem


def decide(explorer: VoronoiExplorer | FrontierExplorer, pose: tuple[float, float, float],
           start: tuple[float, float, float] | None = None,
           visited: VisitedTargets | None = None, **kw: Any) -> Decision:
    out = explorer.decide(t_corridor(), pose, start or pose, visited or VisitedTargets(), **kw)
    assert isinstance(out, Decision), out
    return out


def test_voronoi_goes_to_nearest_open_end_with_lambda_one() -> None:
    d = decide(VoronoiExplorer(ExplorerParams(lam=1.0)), LEFT_START)
    assert d.reason == "voronoi"
    assert d.target_xy[0] < 2.5
    assert np.allclose(d.path.xy_m[0], LEFT_START[:2]) and np.allclose(d.path.xy_m[-1],
                                                                       d.target_xy)
    ok = [t for t in d.candidates if t.status == "ok"]
    # both open ends, each as a rule-1 junction and as a frontier cluster (pooled with λ > 0)
    assert sorted(t.kind for t in ok) == ["frontier", "frontier", "voronoi", "voronoi"]
    chosen = min(ok, key=lambda t: t.cost)
    assert chosen.xy == d.target_xy and chosen.cost == pytest.approx(chosen.d_robot_m)
    # d_robot is a path length: at least the straight-line distance, at most a bit more here.
    straight = np.hypot(d.target_xy[0] - LEFT_START[0], d.target_xy[1] - LEFT_START[1])
    assert straight - 1e-9 <= chosen.d_robot_m <= straight + 0.3


def test_lambda_zero_prefers_targets_near_the_start() -> None:
    # The robot stands near the right end but started near the left one.
    d = decide(VoronoiExplorer(ExplorerParams(lam=0.0)), (9.0, 3.75, 0.0), start=LEFT_START)
    assert d.target_xy[0] < 2.5
    d1 = decide(VoronoiExplorer(ExplorerParams(lam=1.0)), (9.0, 3.75, 0.0), start=LEFT_START)
    assert d1.target_xy[0] > 9.5


def test_visited_and_reserved_targets_are_skipped() -> None:
    ex = VoronoiExplorer()
    first = decide(ex, LEFT_START)
    visited = VisitedTargets(radius_m=1.0, points_xy=[first.target_xy])
    second = decide(ex, LEFT_START, visited=visited)
    assert second.target_xy[0] > 9.5
    # the left end's frontier, still open next to where the robot stood, no longer counts
    assert not any(t.xy[0] < 2.5 and t.status == "ok" for t in second.candidates)
    reserved = decide(ex, LEFT_START, reserved_xy=[first.target_xy])
    assert reserved.target_xy[0] > 9.5
    assert any(t.status == "reserved" for t in reserved.candidates)


def test_junctions_first_unless_pooled() -> None:
    # λ = 0: junctions first (the dissertation's order), frontier clusters never scored here.
    d0 = decide(VoronoiExplorer(ExplorerParams(lam=0.0)), LEFT_START)
    assert {t.kind for t in d0.candidates} == {"voronoi"}
    pooled = decide(VoronoiExplorer(ExplorerParams(lam=0.0, pool_groups=True)), LEFT_START)
    assert {t.kind for t in pooled.candidates} == {"voronoi", "frontier"}
    assert ExplorerParams(lam=0.5).pooled and not ExplorerParams(lam=1.0, pool_groups=False).pooled


def test_frontier_targets_when_the_skeleton_offers_none() -> None:
    # With a huge ridge separation there is no skeleton at all, so no rule-1 junction.
    params = ExplorerParams(analysis=AnalysisParams(min_separation_m=100.0))
    d = decide(VoronoiExplorer(params), LEFT_START)
    assert d.reason == "frontier"
    assert d.target_xy[0] < 1.6


def test_frontier_explorer_takes_nearest_frontier() -> None:
    ex = make_explorer("frontier")
    assert isinstance(ex, FrontierExplorer)
    assert decide(ex, LEFT_START).target_xy[0] < 1.6
    assert decide(ex, (9.0, 3.75, 0.0)).target_xy[0] > 10.4
    with pytest.raises(ValueError, match="unknown explorer"):
        make_explorer("random")


def test_unreachable_frontier_is_not_chosen() -> None:
    # Wall off the left end just inside the corridor: its frontier is unreachable.
    g = t_corridor()
    data = g.data.copy()
    data[30:45, 20] = 100
    grid = OccupancyGrid(data, g.resolution_m, g.origin_xy)
    out = VoronoiExplorer().decide(grid, LEFT_START, LEFT_START, VisitedTargets())
    assert isinstance(out, Decision) and out.target_xy[0] > 9.5
    assert any(t.status == "unreachable" for t in out.candidates)


def test_finished_when_no_frontier_or_coverage_reached() -> None:
    g = t_corridor()
    data = g.data.copy()
    data[30:45, 10] = 100
    data[30:45, 109] = 100
    closed = OccupancyGrid(data, g.resolution_m, g.origin_xy)
    out = VoronoiExplorer().decide(closed, LEFT_START, LEFT_START, VisitedTargets())
    assert isinstance(out, Finished) and out.reason == "no frontier left"
    # Both open ends visited: frontiers remain but none is reachable as a new target.
    visited = VisitedTargets(1.0, [(1.5, 3.75), (10.5, 3.75)])
    keep_seen = ExplorerParams(analysis=AnalysisParams(seen_radius_m=0.0))
    out = VoronoiExplorer(keep_seen).decide(g, LEFT_START, LEFT_START, visited)
    assert isinstance(out, Finished) and out.reason == "no reachable frontier"
    assert out.candidates and all(t.status != "ok" for t in out.candidates)
    # By default frontier cells next to visited targets are settled: nothing is left.
    out = VoronoiExplorer().decide(g, LEFT_START, LEFT_START, visited)
    assert isinstance(out, Finished) and out.reason == "no frontier left"
    area = explored_area_m2(g)
    done = VoronoiExplorer(ExplorerParams(total_area_m2=area / 0.97, coverage_threshold=0.96))
    out = done.decide(g, LEFT_START, LEFT_START, VisitedTargets())
    assert isinstance(out, Finished) and out.coverage == pytest.approx(0.97)
    going = VoronoiExplorer(ExplorerParams(total_area_m2=area / 0.95, coverage_threshold=0.96))
    assert isinstance(going.decide(g, LEFT_START, LEFT_START, VisitedTargets()), Decision)


def test_start_inside_a_wall_raises_start_occupied() -> None:
    with pytest.raises(StartOccupied):
        VoronoiExplorer().decide(t_corridor(), (3.0, 7.0, 0.0), (3.0, 7.0, 0.0),
                                 VisitedTargets())


def test_coverage_arithmetic() -> None:
    d = np.full((10, 20), -1, np.int8)
    d[:, :5] = 0          # 50 free
    d[:, 5] = 100         # 10 occupied
    d[:, 6] = 55          # 10 uncertain: not explored
    g = OccupancyGrid(d, 0.5, (0.0, 0.0))
    assert explored_area_m2(g) == pytest.approx(60 * 0.25)
    assert coverage(g, 30.0) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        coverage(g, 0.0)


def test_visited_targets_radius_and_sharing() -> None:
    a = VisitedTargets(radius_m=1.0, points_xy=[(0.0, 0.0)])
    b = VisitedTargets(radius_m=1.0, points_xy=[(5.0, 5.0)])
    assert (0.9, 0.0) in a and (1.1, 0.0) not in a
    a.update(b)
    assert len(a) == 2 and (5.5, 5.0) in a
    assert a.mask([(0, 0.5), (3, 3), (5, 4.2)]).tolist() == [True, False, True]
    with pytest.raises(ValueError):
        a.add((np.nan, 0.0))


def brute_force_assignment(cost: np.ndarray) -> float:
    R, K = cost.shape
    best = np.inf
    for cols in itertools.permutations(range(K), R):
        best = min(best, sum(cost[r, c] for r, c in enumerate(cols)))
    return best


@pytest.mark.parametrize("seed", range(10))
def test_optimal_assignment_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = int(rng.integers(1, 4))
    K = int(rng.integers(R, 6))
    cost = rng.uniform(0, 10, (R, K))
    got = assign_optimal(cost)
    assert len(set(got)) == R and None not in got
    total = sum(cost[r, c] for r, c in enumerate(got) if c is not None)
    assert total == pytest.approx(brute_force_assignment(cost))


def test_optimal_assignment_with_unreachable_targets() -> None:
    inf = np.inf
    cost = np.array([[1.0, inf], [2.0, inf], [inf, inf]])
    got = assign_optimal(cost)
    assert got.count(0) == 1 and got[2] is None and 1 not in got
    assert got[0] == 0  # robot 0 is cheaper on target 0


def test_separated_rule_keeps_goals_two_metres_apart() -> None:
    targets = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0]])
    cost = np.array([[1.0, 2.0, 9.0],
                     [1.0, 1.5, 8.0]])
    # Robot 1's cheapest targets are within 2 m of robot 0's goal (0, 0): it gets (5, 0).
    assert assign_separated(cost, targets, 2.0) == [0, 2]
    assert assign_separated(cost, targets, 0.5) == [0, 1]
    assert assign_separated(cost[:, :2], targets[:2], 2.0) == [0, None]


def test_team_costs_send_robots_to_different_ends() -> None:
    ex = VoronoiExplorer(ExplorerParams(pool_groups=False))
    poses = [LEFT_START, (9.0, 3.75, 0.0)]
    team = ex.team_costs(t_corridor(), poses, poses, VisitedTargets())
    assert team.kind == "voronoi" and team.cost.shape == (2, 2)
    got = assign_optimal(team.cost)
    goals = [team.targets_xy[k][0] for k in got if k is not None]
    assert goals[0] < 2.5 and goals[1] > 9.5
    path = team.path(1, got[1] if got[1] is not None else 0)
    assert np.allclose(path.xy_m[0], poses[1][:2])


def test_pooled_team_costs_hold_every_group_and_still_split_the_robots() -> None:
    ex = VoronoiExplorer(ExplorerParams(lam=1.0))       # λ > 0: groups pooled, as in decide
    poses = [LEFT_START, (9.0, 3.75, 0.0)]
    team = ex.team_costs(t_corridor(), poses, poses, VisitedTargets())
    alone = VoronoiExplorer(ExplorerParams(pool_groups=False)).team_costs(
        t_corridor(), poses, poses, VisitedTargets())
    assert team.kind.startswith("voronoi") and team.cost.shape[1] > alone.cost.shape[1]
    got = assign_optimal(team.cost)
    assert None not in got and got[0] != got[1]
    xs = [team.targets_xy[k][0] for k in got if k is not None]
    assert xs[0] < xs[1]       # the left robot takes a target left of the right robot's
