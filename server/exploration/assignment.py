"""Assigning a team's robots to targets, given a cost matrix robots × targets.

Costs are any non-negative scores (e.g. C = λ·d_robot + (1−λ)·d_origin); ∞ marks a target a
robot cannot reach. Both functions return, for each robot, a target index or None.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

# Stands in for ∞ inside the solver (which rejects infeasible matrices); pairs at this cost
# are dropped from the answer.
_BIG = 1e12


def assign_optimal(cost: ArrayLike) -> list[int | None]:
    """Minimum total cost one-to-one assignment (Hungarian method, scipy's
    ``linear_sum_assignment``). With more robots than reachable targets some robots get None."""
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"cost matrix must be 2-D, got shape {c.shape}")
    out: list[int | None] = [None] * c.shape[0]
    if c.size == 0:
        return out
    if np.isnan(c).any():
        raise ValueError("cost matrix contains NaN")
    finite = np.isfinite(c)
    rows, cols = linear_sum_assignment(np.where(finite, c, _BIG))
    for r, k in zip(rows, cols, strict=True):
        if finite[r, k]:
            out[int(r)] = int(k)
    return out


def assign_separated(cost: ArrayLike, targets_xy: ArrayLike,
                     min_separation_m: float = 2.0) -> list[int | None]:
    """The dissertation's rule: robots choose in order; each takes its cheapest target at least
    ``min_separation_m`` from the goals already taken (None when there is none)."""
    c = np.asarray(cost, dtype=np.float64)
    xy: NDArray[np.float64] = np.asarray(targets_xy, dtype=np.float64).reshape(-1, 2)
    if c.ndim != 2 or c.shape[1] != len(xy):
        raise ValueError(f"cost {c.shape} does not match {len(xy)} targets")
    out: list[int | None] = []
    taken: list[int] = []
    for row in c:
        ok = np.isfinite(row)
        for k in taken:
            ok &= np.hypot(*(xy - xy[k]).T) >= min_separation_m
        if not ok.any():
            out.append(None)
            continue
        best = int(np.flatnonzero(ok)[np.argmin(row[ok])])
        out.append(best)
        taken.append(best)
    return out
