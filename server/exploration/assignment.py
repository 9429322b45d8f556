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


def assign_spread(cost: ArrayLike, targets_xy: ArrayLike,
                  min_separation_m: float = 2.0,
                  also_near: NDArray[np.bool_] | None = None) -> list[int | None]:
    """Minimum total cost assignment in which no two robots take targets closer than
    ``min_separation_m`` while each could take another: two targets that close open onto
    the same unexplored space, and robots sent there together find little more than one
    robot would. Where two assigned targets clash, the robot whose giving way costs the
    team less takes its best target elsewhere; a robot with nothing elsewhere shares.
    ``also_near`` (K, K) marks further pairs of targets that clash however far apart."""
    c = np.array(cost, dtype=np.float64)
    xy: NDArray[np.float64] = np.asarray(targets_xy, dtype=np.float64).reshape(-1, 2)
    if c.ndim != 2 or c.shape[1] != len(xy):
        raise ValueError(f"cost {c.shape} does not match {len(xy)} targets")
    near = np.hypot(xy[:, None, 0] - xy[None, :, 0],
                    xy[:, None, 1] - xy[None, :, 1]) < min_separation_m
    if also_near is not None:
        if also_near.shape != near.shape:
            raise ValueError(f"also_near {also_near.shape} does not match {len(xy)} targets")
        near = near | also_near
    out = assign_optimal(c)
    shared: set[tuple[int, int]] = set()
    for _ in range(c.shape[0] * c.shape[0]):
        taken = [(i, k) for i, k in enumerate(out) if k is not None]
        clash = next(((a, b) for n, a in enumerate(taken) for b in taken[n + 1:]
                      if near[a[1], b[1]] and (a[0], b[0]) not in shared), None)
        if clash is None:
            break
        options = []
        for (i, _), (_, k_keep) in (clash, clash[::-1]):
            trial = c.copy()
            trial[i, near[k_keep]] = np.inf
            if not np.isfinite(trial[i]).any():
                continue
            alt = assign_optimal(trial)
            if alt[i] is None:
                continue
            got = [(r, k) for r, k in enumerate(alt) if k is not None]
            options.append(((-len(got), sum(trial[r, k] for r, k in got)), i, k_keep, alt))
        if not options:
            shared.add((clash[0][0], clash[1][0]))
            continue
        _, i, k_keep, out = min(options, key=lambda o: o[0])
        c[i, near[k_keep]] = np.inf
    return out
