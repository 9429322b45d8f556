"""A* and the one-to-many Dijkstra: optimality, typed failures, clearance, shortcutting."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.planning import (
    CostField,
    CostParams,
    GoalOccupied,
    NoPath,
    OccupancyGrid,
    OutsideGrid,
    PlanningTimedOut,
    StartOccupied,
    astar_cells,
    build_cost_layer,
    plan,
)
from server.planning.path import shortcut_cells

SQ2 = math.sqrt(2.0)
OFFSETS = [(0, 1, 1.0), (0, -1, 1.0), (1, 0, 1.0), (-1, 0, 1.0),
           (1, 1, SQ2), (1, -1, SQ2), (-1, 1, SQ2), (-1, -1, SQ2)]


def brute_force_costs(cost: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """All-cells minimum costs by Bellman–Ford relaxation until nothing changes (no heap, no
    heuristic): an independent reference for A*."""
    H, W = cost.shape
    dist = np.full((H, W), np.inf)
    dist[start] = 0.0
    while True:
        before = dist.copy()
        for dr, dc, step in OFFSETS:
            # Relax every edge (r - dr, c - dc) -> (r, c).
            src = np.full((H, W), np.inf)
            srcc = np.full((H, W), np.inf)
            rs = slice(max(0, dr), H + min(0, dr))
            cs = slice(max(0, dc), W + min(0, dc))
            rs0 = slice(max(0, -dr), H - max(0, dr))
            cs0 = slice(max(0, -dc), W - max(0, dc))
            src[rs, cs] = dist[rs0, cs0]
            srcc[rs, cs] = cost[rs0, cs0]
            cand = src + step * 0.5 * (srcc + cost)
            cand[~np.isfinite(cost)] = np.inf
            dist = np.minimum(dist, cand)
        if np.array_equal(dist, before):
            return dist


def path_cost(cost: np.ndarray, cells: np.ndarray) -> float:
    d = np.diff(cells, axis=0)
    assert np.all(np.abs(d) <= 1) and np.all(np.any(d != 0, axis=1)), "not 8-connected"
    step = np.where(np.all(d != 0, axis=1), SQ2, 1.0)
    c = cost[cells[:, 0], cells[:, 1]]
    assert np.all(np.isfinite(c)), "path crosses a lethal cell"
    return float(np.sum(step * 0.5 * (c[:-1] + c[1:])))


@pytest.mark.parametrize("seed", range(12))
def test_astar_is_optimal_on_random_grids(seed: int) -> None:
    rng = np.random.default_rng(seed)
    H, W = rng.integers(6, 16, 2)
    cost = rng.uniform(1.0, 5.0, (H, W))
    cost[rng.random((H, W)) < 0.25] = np.inf
    free = np.argwhere(np.isfinite(cost))
    s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
    ref = brute_force_costs(cost, s)
    if not np.isfinite(ref[g]):
        with pytest.raises(NoPath):
            astar_cells(cost, s, g, min_cost=1.0)
        return
    cells, total = astar_cells(cost, s, g, min_cost=1.0)
    assert tuple(cells[0]) == s and tuple(cells[-1]) == g
    assert total == pytest.approx(ref[g], rel=1e-9)
    assert path_cost(cost, cells) == pytest.approx(total, rel=1e-9)


def test_dijkstra_field_matches_brute_force_and_astar() -> None:
    rng = np.random.default_rng(42)
    d = np.zeros((30, 30), np.int8)
    d[rng.random((30, 30)) < 0.08] = 100
    g = OccupancyGrid(d, 0.1, (0.0, 0.0))
    layer = build_cost_layer(g, CostParams(robot_radius_m=0.05, safety_margin_m=0.2))
    free = np.argwhere(np.isfinite(layer.cost))
    s = tuple(int(v) for v in free[0])
    start_xy = g.geometry.cell_to_world(s)
    ref = brute_force_costs(layer.cost, s)
    field = CostField(layer, start_xy)
    goals = free[rng.choice(len(free), 20, replace=False)]
    goals_xy = g.geometry.cell_to_world(goals)
    got = field.costs_m(goals_xy)
    assert np.allclose(got, ref[goals[:, 0], goals[:, 1]] * 0.1)
    for xy in goals_xy[np.isfinite(got)][:5]:
        assert plan(layer, start_xy, xy, smooth=False).cost == pytest.approx(
            field.path_to(xy, smooth=False).cost)


def test_early_stopped_field_still_answers_other_cells() -> None:
    d = np.zeros((40, 40), np.int8)
    g = OccupancyGrid(d, 0.1, (0.0, 0.0))
    layer = build_cost_layer(g, CostParams())
    field = CostField(layer, (0.5, 0.5), goals_xy=[(0.8, 0.8)])
    far = field.costs_m([(3.85, 3.85)])[0]
    assert np.isfinite(far) and far == pytest.approx(3.3 * SQ2, rel=1e-6)


def corridor_grid() -> OccupancyGrid:
    """A 4 m × 2 m room (5 cm cells) split by a wall with a 0.6 m door at its top end."""
    d = np.zeros((40, 80), np.int8)
    d[0, :] = d[-1, :] = d[:, 0] = d[:, -1] = 100
    d[:28, 40] = 100
    return OccupancyGrid(d, 0.05, (0.0, 0.0))


def test_typed_failures() -> None:
    g = corridor_grid()
    layer = build_cost_layer(g, CostParams())
    with pytest.raises(OutsideGrid):
        plan(layer, (-1.0, 0.5), (3.0, 0.5))
    with pytest.raises(OutsideGrid):
        plan(layer, (0.5, 0.5), (30.0, 0.5))
    with pytest.raises(GoalOccupied):
        plan(layer, (0.5, 0.5), (2.02, 0.5))          # on the dividing wall
    with pytest.raises(StartOccupied):
        plan(layer, (2.02, 0.5), (3.0, 0.5), escape_radius_m=0.05)
    closed = g.data.copy()
    closed[:, 40] = 100
    closed_layer = build_cost_layer(OccupancyGrid(closed, 0.05, (0.0, 0.0)), CostParams())
    with pytest.raises(NoPath):
        plan(closed_layer, (0.5, 0.5), (3.0, 0.5))
    with pytest.raises(NoPath):
        CostField(closed_layer, (0.5, 0.5)).path_to((3.0, 0.5))
    with pytest.raises(PlanningTimedOut):
        plan(layer, (0.5, 0.5), (3.0, 0.5), timeout_s=0.0)


def test_start_near_wall_escapes_instead_of_failing() -> None:
    layer = build_cost_layer(corridor_grid(), CostParams())
    start = (1.93, 0.5)                                 # 0.05 m from the dividing wall
    path = plan(layer, start, (0.5, 1.0))
    assert tuple(path.xy_m[0]) == start
    first = layer.geometry.world_to_cell(path.xy_m[1])
    assert np.isfinite(layer.cost[tuple(first)])
    assert np.hypot(*(path.xy_m[1] - path.xy_m[0])) <= 0.5


def min_wall_distance(g: OccupancyGrid, xy: np.ndarray) -> float:
    """Smallest distance from points to the edge of any occupied cell [m]."""
    occ = g.geometry.cell_to_world(np.argwhere(g.occupied))
    half = g.resolution_m / 2
    dx = np.maximum(np.abs(xy[:, None, 0] - occ[None, :, 0]) - half, 0)
    dy = np.maximum(np.abs(xy[:, None, 1] - occ[None, :, 1]) - half, 0)
    return float(np.min(np.hypot(dx, dy)))


@pytest.mark.parametrize("smooth", [False, True])
def test_paths_keep_robot_radius_from_walls(smooth: bool) -> None:
    g = corridor_grid()
    params = CostParams(robot_radius_m=0.13)
    layer = build_cost_layer(g, params)
    path = plan(layer, (0.5, 0.5), (3.5, 0.5), smooth=smooth)
    # Densely sample the polyline the robot will follow, not only its vertices.
    pts = np.concatenate([np.linspace(a, b, 20) for a, b in zip(path.xy_m[:-1], path.xy_m[1:],
                                                                  strict=True)])
    assert min_wall_distance(g, pts) >= 0.13 - 1e-9
    # The path goes through the door (y > 1.4 m) since the wall blocks everything below.
    assert pts[:, 1].max() > 1.4


def test_shortcutting_shortens_without_raising_cost() -> None:
    d = np.zeros((60, 60), np.int8)
    d[0, :] = d[-1, :] = d[:, 0] = d[:, -1] = 100
    g = OccupancyGrid(d, 0.05, (0.0, 0.0))
    layer = build_cost_layer(g, CostParams())
    raw = plan(layer, (0.6, 0.6), (2.4, 1.5), smooth=False)
    smooth = plan(layer, (0.6, 0.6), (2.4, 1.5), smooth=True)
    assert smooth.length_m <= raw.length_m + 1e-9
    assert len(smooth.xy_m) < len(raw.xy_m)
    # In open space away from walls the shortcut path is the straight line.
    assert smooth.length_m == pytest.approx(np.hypot(1.8, 0.9), abs=0.06)
    cells = layer.geometry.world_to_cell(raw.xy_m[1:-1])
    kept = shortcut_cells(layer, cells)
    assert tuple(kept[0]) == tuple(cells[0]) and tuple(kept[-1]) == tuple(cells[-1])


def reference_astar(cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int],
                    min_cost: float) -> list[tuple[int, int]]:
    """The search as a plain Python loop over heapq: what the compiled one must equal."""
    import heapq
    import math

    H, W = cost.shape
    W2 = W + 2
    padded = np.full((H + 2, W2), np.inf)
    padded[1:-1, 1:-1] = cost
    c = padded.ravel().tolist()
    s = (start[0] + 1) * W2 + start[1] + 1
    gi = (goal[0] + 1) * W2 + goal[1] + 1
    gr, gc = goal[0] + 1, goal[1] + 1
    r2 = math.sqrt(2.0)
    nbrs = [(1, 1.0), (-1, 1.0), (W2, 1.0), (-W2, 1.0), (W2 + 1, r2), (W2 - 1, r2),
            (-W2 + 1, r2), (-W2 - 1, r2)]
    g = [math.inf] * len(c)
    parent = [-1] * len(c)
    closed = bytearray(len(c))
    g[s] = 0.0
    heap = [(0.0, s)]
    diag = r2 - 1.0
    while heap:
        _, u = heapq.heappop(heap)
        if closed[u]:
            continue
        if u == gi:
            break
        closed[u] = 1
        for off, step in nbrs:
            v = u + off
            if c[v] == math.inf or closed[v]:
                continue
            ng = g[u] + step * 0.5 * (c[u] + c[v])
            if ng < g[v]:
                g[v], parent[v] = ng, u
                dr, dc = abs(v // W2 - gr), abs(v % W2 - gc)
                h = (dr + dc + diag * min(dr, dc) - min(dr, dc)) * min_cost
                heapq.heappush(heap, (ng + h, v))
    else:
        return []
    out, u = [], gi
    while u != -1:
        out.append((u // W2 - 1, u % W2 - 1))
        u = parent[u]
    return out[::-1]


@pytest.mark.parametrize("seed", range(40))
def test_the_compiled_search_finds_the_very_path_of_the_reference_loop(seed: int) -> None:
    """Equal costs everywhere make ties at every step: the compiled heap must break them as
    heapq does, or the robots' paths (and a lockstep run) would change."""
    rng = np.random.default_rng(seed)
    H, W = rng.integers(5, 60, 2)
    cost = rng.choice([1.0, 1.0, 1.0, 2.0, 3.5], (H, W))
    cost[rng.random((H, W)) < 0.2] = np.inf
    free = np.argwhere(np.isfinite(cost))
    s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
    want = reference_astar(cost, s, g, 1.0)
    if not want:
        with pytest.raises(NoPath):
            astar_cells(cost, s, g, min_cost=1.0)
        return
    cells, _ = astar_cells(cost, s, g, min_cost=1.0)
    assert [tuple(int(v) for v in c) for c in cells] == want
