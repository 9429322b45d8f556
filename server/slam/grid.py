"""Log-odds occupancy grid with vectorised ray updates.

Row index = y, column index = x; ``origin`` is the world (x, y) of the lower-left corner of cell
(0, 0), as in nav2's map YAML. Each scan adds l_hit = log(p_hit / (1 − p_hit)) to the cells of
its endpoints and l_miss = log(p_miss / (1 − p_miss)) once to every other cell its rays cross;
log-odds are clamped to [logit(p_min), logit(p_max)] so the map stays revisable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.occupancy import FREE_BELOW, OCCUPIED, OCCUPIED_ABOVE, UNKNOWN

F64 = NDArray[np.float64]


def logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class GridParams:
    resolution_m: float = 0.05
    p_hit: float = 0.75
    p_miss: float = 0.35
    p_min: float = 0.12
    p_max: float = 0.97
    free_below: float = FREE_BELOW / OCCUPIED
    occupied_above: float = OCCUPIED_ABOVE / OCCUPIED
    max_ray_m: float = 20.0
    padding_m: float = 2.0


class OccupancyGrid:
    """A growable log-odds grid. ``log_odds`` (H, W) float32, ``observed`` (H, W) bool."""

    def __init__(self, params: GridParams, origin_xy: tuple[float, float] = (0.0, 0.0),
                 shape_hw: tuple[int, int] = (0, 0)) -> None:
        self.params = params
        self.resolution_m = params.resolution_m
        self.origin = np.array(origin_xy, dtype=np.float64)
        self.log_odds = np.zeros(shape_hw, dtype=np.float32)
        self.observed = np.zeros(shape_hw, dtype=bool)
        self._scratch = np.zeros(0, dtype=bool)
        self._l_hit = logit(params.p_hit)
        self._l_miss = logit(params.p_miss)
        self._l_min = logit(params.p_min)
        self._l_max = logit(params.p_max)

    @classmethod
    def covering(cls, params: GridParams, lo_xy: F64, hi_xy: F64) -> OccupancyGrid:
        """An empty grid covering the box [lo, hi] plus the padding, aligned to the resolution."""
        res = params.resolution_m
        lo = np.floor((np.asarray(lo_xy) - params.padding_m) / res) * res
        hi = np.asarray(hi_xy) + params.padding_m
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        return cls(params, (float(lo[0]), float(lo[1])), (max(h, 1), max(w, 1)))

    @property
    def origin_pose(self) -> tuple[float, float, float]:
        """nav2 ``origin``: world (x, y, θ = 0) of the lower-left corner of cell (0, 0)."""
        return (float(self.origin[0]), float(self.origin[1]), 0.0)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.log_odds.shape[0]), int(self.log_odds.shape[1]))

    def cell_of(self, xy: F64) -> NDArray[np.int64]:
        """(N, 2) integer (ix, iy) of world points."""
        return np.floor((np.asarray(xy) - self.origin) / self.resolution_m).astype(np.int64)

    def ensure_contains(self, lo_xy: F64, hi_xy: F64) -> None:
        """Grow (keeping content) so that the box [lo, hi] lies inside the grid."""
        res = self.resolution_m
        h, w = self.shape
        pad = self.params.padding_m
        if h * w == 0:
            fresh = OccupancyGrid.covering(self.params, np.asarray(lo_xy), np.asarray(hi_xy))
            self.log_odds, self.observed, self.origin = fresh.log_odds, fresh.observed, fresh.origin
            return
        hi_grid = self.origin + np.array([w, h]) * res
        if np.all(lo_xy >= self.origin) and np.all(hi_xy < hi_grid):
            return
        new_lo = np.minimum(self.origin, np.floor((np.asarray(lo_xy) - pad) / res) * res)
        new_hi = np.maximum(hi_grid, np.asarray(hi_xy) + pad)
        nw, nh = (np.ceil((new_hi - new_lo) / res).astype(int) + 1).tolist()
        ox, oy = np.round((self.origin - new_lo) / res).astype(int).tolist()
        lo_new = np.zeros((nh, nw), dtype=np.float32)
        ob_new = np.zeros((nh, nw), dtype=bool)
        lo_new[oy:oy + h, ox:ox + w] = self.log_odds
        ob_new[oy:oy + h, ox:ox + w] = self.observed
        self.log_odds, self.observed, self.origin = lo_new, ob_new, new_lo

    def insert_scan(self, T_world_sensor: F64, hits_sensor: F64,
                    misses_sensor: F64 | None = None) -> None:
        """Update with one scan: ``hits_sensor`` (N, 2) endpoints in the sensor frame;
        ``misses_sensor`` (M, 2) optional points of beams without a return, only cleared to."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        c, s = math.cos(T[2]), math.sin(T[2])
        R = np.array([[c, -s], [s, c]])
        hits = np.asarray(hits_sensor, dtype=np.float64).reshape(-1, 2)
        ends = hits @ R.T + T[:2]
        rays = ends
        if misses_sensor is not None and len(misses_sensor):
            rays = np.concatenate([ends, np.asarray(misses_sensor).reshape(-1, 2) @ R.T + T[:2]])
        if len(rays) == 0:
            return
        # clip free-space rays to max_ray_m
        vec = rays - T[:2]
        length = np.hypot(vec[:, 0], vec[:, 1])
        scale = np.minimum(1.0, self.params.max_ray_m / np.maximum(length, 1e-9))
        rays = T[:2] + vec * scale[:, None]
        lo = np.minimum(np.minimum(rays.min(axis=0), T[:2]), ends.min(axis=0, initial=np.inf))
        hi = np.maximum(np.maximum(rays.max(axis=0), T[:2]), ends.max(axis=0, initial=-np.inf))
        self.ensure_contains(lo, hi)
        res = self.resolution_m
        h, w = self.shape
        # sample each ray every 0.7 cell (a ray crossing a cell's corner may skip it; other
        # rays and scans fill it), stopping short of its end cell
        step = 0.7 * res
        lengths = length * scale
        n_samp = np.ceil(lengths / step).astype(np.int64)
        total = int(n_samp.sum())
        if total:
            ray_id = np.repeat(np.arange(len(rays)), n_samp)
            first = np.cumsum(n_samp) - n_samp
            k = np.arange(total) - np.repeat(first, n_samp)
            frac = (k * step) / np.maximum(lengths[ray_id], 1e-9)
            px = T[0] + frac * (rays[ray_id, 0] - T[0])
            py = T[1] + frac * (rays[ray_id, 1] - T[1])
            ix = np.floor((px - self.origin[0]) / res).astype(np.int64)
            iy = np.floor((py - self.origin[1]) / res).astype(np.int64)
            free = iy * w + ix
        else:
            free = np.zeros(0, dtype=np.int64)
        hit_cells = self.cell_of(ends)
        hit = hit_cells[:, 1] * w + hit_cells[:, 0]
        flat_lo = self.log_odds.reshape(-1)
        flat_ob = self.observed.reshape(-1)
        # a cell is updated once per scan however many rays cross it (assignment through
        # repeated indices writes the same value), and endpoints are not freed
        if self._scratch.size != h * w:
            self._scratch = np.zeros(h * w, dtype=bool)
        is_hit = self._scratch
        is_hit[hit] = True
        free = free[~is_hit[free]]
        is_hit[hit] = False
        flat_lo[free] = np.maximum(flat_lo[free] + self._l_miss, self._l_min)
        flat_lo[hit] = np.minimum(flat_lo[hit] + self._l_hit, self._l_max)
        flat_ob[free] = True
        flat_ob[hit] = True

    def probability(self) -> NDArray[np.float32]:
        """Occupancy probability per cell (0.5 where unobserved)."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def to_nav2(self) -> NDArray[np.int8]:
        """int8 (H, W): −1 unknown, else occupancy in percent (0..100)."""
        pct = np.rint(self.probability() * OCCUPIED).astype(np.int8)
        return np.where(self.observed, pct, np.int8(UNKNOWN)).astype(np.int8)

    def free_mask(self) -> NDArray[np.bool_]:
        return self.observed & (self.probability() < self.params.free_below)

    def occupied_mask(self) -> NDArray[np.bool_]:
        return self.observed & (self.probability() > self.params.occupied_above)
