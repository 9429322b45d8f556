"""Planned paths and their shortcutting."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.planning.costmap import CostLayer


def polyline_length_m(xy: NDArray[np.float64]) -> float:
    """Σ ‖p_{i+1} − p_i‖ of a polyline (N, 2) [m]."""
    if len(xy) < 2:
        return 0.0
    return float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))


@dataclass(frozen=True, eq=False)
class Path:
    """World waypoints (N, 2) [m] from the start to the goal.

    ``cost`` is the planner's cost of the cell path it found [m-equivalents: Σ step_m · mean
    cell cost], before any shortcutting; ``length_m`` is the length of ``xy_m`` as returned.
    """

    xy_m: NDArray[np.float64]
    cost: float
    length_m: float

    @classmethod
    def from_points(cls, xy_m: ArrayLike, cost: float) -> Path:
        xy = np.asarray(xy_m, dtype=np.float64).reshape(-1, 2)
        return cls(xy_m=xy, cost=float(cost), length_m=polyline_length_m(xy))

    @property
    def goal_xy(self) -> tuple[float, float]:
        return float(self.xy_m[-1, 0]), float(self.xy_m[-1, 1])


def _segment_ok(cost: NDArray[np.float64], a: NDArray[np.int64], b: NDArray[np.int64],
                limit: float) -> bool:
    """Whether every cell the straight segment between cell centres a and b crosses costs
    ≤ ``limit`` (sampled every 1/3 cell)."""
    n = int(np.ceil(3 * np.hypot(*(b - a).astype(np.float64)))) + 1
    t = np.linspace(0.0, 1.0, n)
    rows = np.floor(a[0] + 0.5 + t * (b[0] - a[0])).astype(np.int64)
    cols = np.floor(a[1] + 0.5 + t * (b[1] - a[1])).astype(np.int64)
    return bool(np.all(cost[rows, cols] <= limit))


def shortcut_cells(layer: CostLayer, cells: NDArray[np.int64]) -> NDArray[np.int64]:
    """A subset of a cell path (N, 2) whose straight segments replace runs of the original.

    From each kept cell, the farthest later cell reachable by a straight segment is kept next
    (searched by doubling then bisection, so a segment may be missed where visibility is not
    monotonic along the path — the result is valid, only less short). A segment is accepted when
    every cell it crosses costs at most max(1, highest cost along the replaced run), so a shortcut
    never brings the robot closer to obstacles or into costlier cells than the path it replaces.
    """
    n = len(cells)
    if n <= 2:
        return cells
    path_cost = layer.cost[cells[:, 0], cells[:, 1]]
    kept = [0]
    a = 0
    while a < n - 1:
        run_max = np.maximum(np.maximum.accumulate(path_cost[a:]), 1.0)

        def ok(j: int, a: int = a, run_max: NDArray[np.float64] = run_max) -> bool:
            return _segment_ok(layer.cost, cells[a], cells[j], float(run_max[j - a]))

        lo, step = a + 1, 1  # lo: farthest cell known reachable
        hi = n  # first cell known unreachable (n = none)
        while True:
            j = min(a + 2 * step, n - 1)
            if j <= lo:
                break
            if ok(j):
                lo = j
                if j == n - 1:
                    break
                step *= 2
            else:
                hi = j
                break
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ok(mid):
                lo = mid
            else:
                hi = mid
        kept.append(lo)
        a = lo
    return cells[np.asarray(kept)]
