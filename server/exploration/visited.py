"""Targets already visited (or given up on), shared by the robots of a team."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray


class VisitedTargets:
    """A set of world points; a point within ``radius_m`` of one of them counts as visited.

    Robots of one team share one instance (after a merge, :meth:`update` folds another robot's
    set in — the points must be in the same frame).
    """

    def __init__(self, radius_m: float = 1.0, points_xy: Iterable[ArrayLike] = ()) -> None:
        if not radius_m >= 0:
            raise ValueError(f"radius_m must be >= 0, got {radius_m}")
        self.radius_m = float(radius_m)
        self._points: list[tuple[float, float]] = []
        for p in points_xy:
            self.add(p)

    def add(self, xy: ArrayLike) -> None:
        p = np.asarray(xy, dtype=np.float64).reshape(2)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"visited target must be finite, got {p}")
        self._points.append((float(p[0]), float(p[1])))

    def update(self, other: VisitedTargets) -> None:
        for p in other.points_xy:
            self.add(p)

    @property
    def points_xy(self) -> NDArray[np.float64]:
        return np.asarray(self._points, dtype=np.float64).reshape(-1, 2)

    def mask(self, xy: ArrayLike) -> NDArray[np.bool_]:
        """For each point (M, 2): whether it lies within ``radius_m`` of a visited target."""
        q = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not self._points or len(q) == 0:
            return np.zeros(len(q), dtype=bool)
        d2 = np.sum((q[:, None, :] - self.points_xy[None, :, :]) ** 2, axis=2)
        return np.asarray(np.any(d2 <= self.radius_m ** 2, axis=1))

    def __contains__(self, xy: object) -> bool:
        return bool(self.mask(np.asarray(xy))[0])

    def __len__(self) -> int:
        return len(self._points)
