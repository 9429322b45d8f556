"""The compiled Dijkstra (``server.planning.field_kernel``) against scikit-image's
``MCP_Geometric``, which it replaced in ``CostField``: the same costs, bit for bit."""

from __future__ import annotations

import itertools

import numpy as np
from skimage.graph import MCP_Geometric

from server.planning.dijkstra import _trace
from server.planning.field_kernel import OFFSETS, cost_field


def _grid(rng: np.random.Generator, shape: tuple[int, int], lethal: float) -> np.ndarray:
    cost = rng.uniform(1.0, 4.0, shape)
    cost[rng.random(shape) < lethal] = np.inf
    # a few runs of equal cost, where paths can tie
    cost[: shape[0] // 3, : shape[1] // 3] = 1.0
    return cost


def test_costs_are_mcp_geometrics_to_the_bit() -> None:
    rng = np.random.default_rng(3)
    cells = 0
    for k in range(12):
        shape = (int(rng.integers(5, 60)), int(rng.integers(5, 60)))
        cost = _grid(rng, shape, lethal=0.1 + 0.03 * k)
        free = np.argwhere(np.isfinite(cost))
        start = tuple(int(v) for v in free[rng.integers(len(free))])
        want, _ = MCP_Geometric(cost, fully_connected=True).find_costs([start])
        got, back = cost_field(cost, start)       # type: ignore[arg-type]
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(want))
        np.testing.assert_array_equal(got[np.isfinite(want)], want[np.isfinite(want)])
        assert got[start] == 0.0 and back[start] == -1
        assert (back[~np.isfinite(got)] == -1).all()
        cells += int(np.isfinite(want).sum())
    assert cells > 3000


def test_a_search_with_ends_settles_them_as_a_full_one() -> None:
    rng = np.random.default_rng(4)
    for _ in range(10):
        cost = _grid(rng, (40, 50), lethal=0.2)
        free = [tuple(int(v) for v in rc) for rc in np.argwhere(np.isfinite(cost))]
        start = free[0]
        ends = [free[int(i)] for i in rng.integers(len(free), size=4)]
        full, _ = cost_field(cost, start)      # type: ignore[arg-type]
        part, back = cost_field(cost, start, ends)   # type: ignore[arg-type]
        mcp, _ = MCP_Geometric(cost, fully_connected=True).find_costs([start], ends,
                                                                       find_all_ends=True)
        for r, c in ends:
            assert part[r, c] == full[r, c] == mcp[r, c]
            if np.isfinite(full[r, c]):
                path = _trace(back, OFFSETS, r, c)
                assert tuple(path[0]) == start and tuple(path[-1]) == (r, c)
                # each step is a neighbour's and the traced costs add up to the field's
                steps = np.diff(path, axis=0)
                assert (np.abs(steps) <= 1).all() and (np.abs(steps).sum(axis=1) > 0).all()
                total = 0.0
                for (r0, c0), (r1, c1) in itertools.pairwise(path):
                    length = np.sqrt(2.0) if r0 != r1 and c0 != c1 else 1.0
                    total = total + length * 0.5 * (cost[r0, c0] + cost[r1, c1])
                assert total == full[r, c]
        # fewer cells settled than a full search when the ends are near
        assert np.isfinite(part).sum() <= np.isfinite(full).sum()


def test_walled_off_cells_stay_unreached() -> None:
    cost = np.ones((9, 9))
    cost[:, 4] = np.inf
    got, back = cost_field(cost, (4, 1))
    assert np.isinf(got[:, 5:]).all() and (back[:, 5:] == -1).all()
    assert np.isfinite(got[:, :4]).all()
    # a corner-to-corner step through a lethal diagonal pair is still a step (as in MCP)
    cost = np.ones((2, 2))
    cost[0, 1] = cost[1, 0] = np.inf
    got, _ = cost_field(cost, (0, 0))
    want, _ = MCP_Geometric(cost, fully_connected=True).find_costs([(0, 0)])
    assert got[1, 1] == want[1, 1] == np.sqrt(2.0)
