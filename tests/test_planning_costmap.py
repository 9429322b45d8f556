"""Grid geometry and the cost layer: conversions, validation, inflation, escape."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.planning import CostParams, GridError, OccupancyGrid, build_cost_layer
from server.planning.grid import small_components


def test_world_cell_round_trip_and_origin() -> None:
    g = OccupancyGrid(np.zeros((40, 60), np.int8), 0.05, (-1.0, 2.0))
    geo = g.geometry
    rng = np.random.default_rng(0)
    rc = np.stack([rng.integers(0, 40, 100), rng.integers(0, 60, 100)], axis=1)
    assert np.array_equal(geo.world_to_cell(geo.cell_to_world(rc)), rc)
    # The lower-left corner of cell (0, 0) is the origin; row index grows with y.
    assert np.allclose(geo.cell_to_world([0, 0]), [-1.0 + 0.025, 2.0 + 0.025])
    assert tuple(geo.world_to_cell([-0.99, 2.0 + 0.05 * 3.5])) == (3, 0)
    assert tuple(geo.world_to_cell([-1.01, 2.0])) == (0, -1)
    assert not geo.contains(geo.world_to_cell([-1.01, 2.0]))


def test_crop_keeps_world_positions() -> None:
    d = np.full((50, 50), -1, np.int8)
    d[10:20, 30:45] = 0
    g = OccupancyGrid(d, 0.1, (1.0, -2.0))
    c = g.crop_to_known(margin_cells=2)
    assert c.data.shape == (14, 19)
    xy = g.geometry.cell_to_world([15, 40])
    assert tuple(c.geometry.world_to_cell(xy)) == (15 - 8, 40 - 28)
    assert c.data[7, 12] == 0


@pytest.mark.parametrize("bad", [
    dict(data=np.zeros((4, 4), np.float32)),
    dict(data=np.zeros((4,), np.int8)),
    dict(data=np.full((4, 4), 101, np.int8)),
    dict(data=np.full((4, 4), -5, np.int8)),
    dict(resolution_m=0.0),
    dict(resolution_m=float("nan")),
    dict(origin_xy=(0.0, float("inf"))),
])
def test_bad_grids_raise_grid_error(bad: dict) -> None:
    kw = dict(data=np.zeros((4, 4), np.int8), resolution_m=0.1, origin_xy=(0.0, 0.0))
    kw.update(bad)
    with pytest.raises(GridError):
        OccupancyGrid(**kw)


def test_cell_classes_follow_thresholds() -> None:
    g = OccupancyGrid(np.array([[-1, 0, 39, 40, 70, 71, 100]], np.int8), 0.1, (0.0, 0.0))
    assert g.free.tolist() == [[False, True, True, False, False, False, False]]
    assert g.occupied.tolist() == [[False, False, False, False, False, True, True]]
    assert g.unobserved.tolist() == [[True, False, False, True, True, False, False]]


def test_small_components_ignore_border_and_large() -> None:
    m = np.zeros((20, 20), bool)
    m[5, 5] = m[5, 6] = True          # small, inside
    m[10:16, 10:16] = True            # large
    m[0, 3] = True                    # small but on the border
    s = small_components(m, 4)
    assert s[5, 5] and s[5, 6]
    assert not s[12, 12] and not s[0, 3]


def test_inflation_lethal_band_and_decay() -> None:
    res = 0.05
    d = np.zeros((60, 60), np.int8)
    d[:, 30] = 100  # a vertical wall at column 30
    params = CostParams(robot_radius_m=0.13, safety_margin_m=0.3, margin_cost=4.0)
    layer = build_cost_layer(OccupancyGrid(d, res, (0.0, 0.0)), params)
    row = layer.cost[30]
    clearance = (np.abs(np.arange(60) - 30) - 0.5) * res
    assert np.all(np.isinf(row[clearance < 0.13]))
    assert np.all(np.isfinite(row[clearance >= 0.13]))
    band = (clearance >= 0.13) & (clearance < 0.43)
    left = np.arange(60) < 30
    # Cost decreases monotonically away from the wall and is 1 beyond the margin.
    band_left = row[band & left]
    assert np.all(np.diff(band_left) > 0)  # columns increase towards the wall
    assert band_left.max() <= 1 + 4.0 + 1e-9 and band_left.min() > 1.0
    assert np.all(row[clearance >= 0.43] == 1.0)


def test_unknown_as_obstacle_or_penalised() -> None:
    d = np.zeros((40, 40), np.int8)
    d[:, 25:] = -1
    g = OccupancyGrid(d, 0.05, (0.0, 0.0))
    lethal = build_cost_layer(g, CostParams(unknown_is_obstacle=True))
    assert np.isinf(lethal.cost[20, 30]) and np.isinf(lethal.cost[20, 24])
    soft = build_cost_layer(g, CostParams(unknown_is_obstacle=False, unknown_cost=3.0))
    assert soft.cost[20, 30] == pytest.approx(3.0)
    assert np.isfinite(soft.cost[20, 24])


def test_beam_gaps_are_not_obstacles() -> None:
    d = np.zeros((40, 40), np.int8)
    d[20, 20] = -1                     # a one-cell gap between beams
    layer = build_cost_layer(OccupancyGrid(d, 0.05, (0.0, 0.0)), CostParams(hole_area_m2=0.01))
    assert np.isfinite(layer.cost[20, 20]) and layer.cost[20, 20] == 1.0


def test_escape_finds_nearest_traversable_cell() -> None:
    d = np.zeros((40, 40), np.int8)
    d[:, 20] = 100
    layer = build_cost_layer(OccupancyGrid(d, 0.05, (0.0, 0.0)), CostParams())
    # Cell (10, 19) is next to the wall: lethal; the nearest traversable cell is on its row.
    assert math.isinf(layer.cost[10, 19])
    out = layer.escape((10, 19), radius_m=0.5)
    assert out is not None and out[0] == 10 and np.isfinite(layer.cost[out])
    assert all(math.isinf(layer.cost[10, c]) for c in range(out[1] + 1, 20))
    assert layer.escape((10, 19), radius_m=0.06) is None
