"""The pass over a known map (extend, ``known_map.inspect``): where a placed robot goes next.

What is to be seen again is what the map's older keyframes saw: the cells (``CELL_M``) of
their returns. A cell is seen again once a new keyframe's beam toward it reaches it (ends there
or beyond). A place worth going to is an older keyframe's place (a robot stood there: it can
be reached), worth the cells of its own returns — what a robot's LIDAR sees from there, on the
old map — not seen again yet and not on another robot's way (the cells of the places the
team's other robots are sent to), per metre of the way there (``TRAVEL_M`` added). A robot
whose place has come to show less than ``MIN_GAIN`` such cells (seen on the way, or by
another robot) is sent on (``stale``). The pass is over once ``known_map.inspected_share`` of
the cells has been seen again, or no place is left worth ``MIN_GAIN`` (what lies behind a
door now closed is never seen again). No I/O here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from server.knownmap.views import reach

F64 = NDArray[np.float64]
Cell = tuple[int, int]
Place = tuple[str, int]          # (ghost, its keyframe)

#: the side of a cell of what is to be seen again [m]
CELL_M = 0.25
#: a place must show at least this many cells not seen again to be gone to
MIN_GAIN = 6
#: a robot is sent on once its place shows less than this share of what it showed when given
STALE_SHARE = 0.25
#: added to the way to a place [m] when its cells are weighed by it
TRAVEL_M = 5.0
#: what a place given to see a change again is recorded as showing (``goal``'s ``urgent``)
URGENT = -1


def cells_of(xy: F64) -> set[Cell]:
    return {(int(c), int(r)) for c, r in np.floor(xy / CELL_M).astype(np.int64)}


@dataclass
class Sweep:
    """The cells still to be seen again and where each robot is sent (module docstring)."""

    todo: set[Cell] | None = None
    total: int = 0
    #: robot -> its place, where it lies, and the cells it showed when given
    goals: dict[str, tuple[Place, tuple[float, float], int]] = field(default_factory=dict)
    tried: set[Place] = field(default_factory=set)
    _views: dict[Place, set[Cell]] = field(default_factory=dict)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_views": {}}

    def start(self, owners: list[Place], hits: Callable[[str, int], F64]) -> None:
        """The cells to see again: those of the older keyframes' returns (once)."""
        if self.todo is not None:
            return
        self.todo = set()
        for p in owners:
            self.todo |= self._view(p, hits)
        self.total = len(self.todo)

    def _view(self, p: Place, hits: Callable[[str, int], F64]) -> set[Cell]:
        v = self._views.get(p)
        if v is None:
            v = self._views[p] = cells_of(hits(*p))
        return v

    def saw(self, prof: F64, T: F64) -> None:
        """A new keyframe (its beams ``prof`` at ``T``): the cells it reaches are seen again."""
        if not self.todo:
            return
        keys = list(self.todo)
        c = (np.array(keys, dtype=np.float64) + 0.5) * CELL_M
        span = float(np.nanmax(prof, initial=0.0))
        near = np.hypot(c[:, 0] - T[0], c[:, 1] - T[1]) <= span + CELL_M
        if not near.any():
            return
        dist, got = reach(prof, T, c[near])
        hit = np.isfinite(got) & (got >= dist - CELL_M)
        for k in np.flatnonzero(near)[hit]:
            self.todo.discard(keys[int(k)])

    def share_seen(self) -> float:
        return 1.0 if not self.total or self.todo is None else 1.0 - len(self.todo) / self.total

    def _gain(self, p: Place, hits: Callable[[str, int], F64], skip: set[Cell]) -> int:
        assert self.todo is not None
        return len((self._view(p, hits) & self.todo) - skip)

    def goal(self, rid: str, pose: F64, owners: list[Place], xy: F64,
             hits: Callable[[str, int], F64], urgent: list[int] | None = None
             ) -> tuple[float, float] | None:
        """``rid``'s next place (``xy``: the places of ``owners``); None: none is worth it.
        ``urgent`` (indices into ``owners``): the nearest of these places not given yet,
        whatever it shows (one that sees a change again)."""
        self.goals.pop(rid, None)
        if urgent is not None:
            near = [j for j in urgent if owners[j] not in self.tried]
            if not near:
                return None
            j = min(near, key=lambda k: float(np.hypot(*(xy[k] - pose[:2]))))
            self.tried.add(owners[j])
            self.goals[rid] = (owners[j], (float(xy[j, 0]), float(xy[j, 1])), URGENT)
            return self.goals[rid][1]
        skip: set[Cell] = set()
        for p, _, _ in self.goals.values():
            skip |= self._view(p, hits)
        best, score, gain = -1, 0.0, 0
        d = np.hypot(xy[:, 0] - pose[0], xy[:, 1] - pose[1])
        for j, p in enumerate(owners):
            if p in self.tried:
                continue
            g = self._gain(p, hits, skip)
            if g >= MIN_GAIN and g / (d[j] + TRAVEL_M) > score:
                best, score, gain = j, g / (d[j] + TRAVEL_M), g
        if best < 0:
            return None
        p = owners[best]
        self.tried.add(p)
        self.goals[rid] = (p, (float(xy[best, 0]), float(xy[best, 1])), gain)
        return self.goals[rid][1]

    def stale(self, rid: str, hits: Callable[[str, int], F64]) -> bool:
        """``rid``'s place shows fewer than ``MIN_GAIN`` cells not seen again by now, or less
        than ``STALE_SHARE`` of those it showed when given (the rest seen on the way)."""
        g = self.goals.get(rid)
        if g is None or self.todo is None or g[2] == URGENT:
            return False
        return self._gain(g[0], hits, set()) < max(MIN_GAIN, STALE_SHARE * g[2])
