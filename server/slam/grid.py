"""Log-odds occupancy grid in tiles, with vectorised ray updates.

Row index = y, column index = x; ``origin`` is the world (x, y) of the lower-left corner of cell
(0, 0), as in nav2's map YAML. Each scan adds l_hit = log(p_hit / (1 − p_hit)) to the cells of
its endpoints and l_miss = log(p_miss / (1 − p_miss)) once to every other cell its rays cross;
log-odds are clamped to [logit(p_min), logit(p_max)] so the map stays revisable.

Storage follows the area observed, not its bounding box: the cells live in square tiles of
``TILE`` × ``TILE`` that are allocated when a ray first touches them, each cell an int16 log-odds
in thousandths (``SCALE``), with one value (``UNKNOWN_Q``) for a cell never observed. The grid's
extent (``origin``, ``shape``) is only a box of numbers; dense arrays (``to_nav2``, the masks) are
made on request, and ``bands`` hands out the map a strip of rows at a time for exports. Returns
farther than ``max_ray_m`` are not mapped (their beams clear free space up to that range), so a
long-range laser does not stretch the map over what it barely saw.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.occupancy import FREE_BELOW, OCCUPIED, OCCUPIED_ABOVE, UNKNOWN
from server.jit import njit_cached
from server.slam.grid_kernel import lattice_slots, ray_cells, update_cells

F64 = NDArray[np.float64]
Points = NDArray[np.floating[Any]]   # (N, 2), single or double precision
I16 = NDArray[np.int16]

_TILE_BITS = 6
TILE = 1 << _TILE_BITS        # cells per tile side: 64 (3.2 m at 5 cm)
SCALE = 1000.0                # int16 units per unit of log-odds
UNKNOWN_Q = np.int16(-32768)  # a cell never observed
_MARK_Q = np.int16(-32767)    # transient: a scan's endpoint while its free cells are chosen


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


def _q(x: float) -> int:
    return round(x * SCALE)


class OccupancyGrid:
    """A growable, tiled log-odds grid. ``shape`` (H, W) and ``origin`` give its extent;
    ``log_odds`` (float32) and ``observed`` (bool) are read-only dense copies."""

    def __init__(self, params: GridParams, origin_xy: tuple[float, float] = (0.0, 0.0),
                 shape_hw: tuple[int, int] = (0, 0)) -> None:
        self.params = params
        self.resolution_m = params.resolution_m
        # cells are counted on a lattice anchored at the first origin; the extent is the
        # lattice box [ex0, ex0 + W) × [ey0, ey0 + H)
        self._anchor = np.array(origin_xy, dtype=np.float64)
        self._ext = np.array([0, 0, int(shape_hw[1]), int(shape_hw[0])], dtype=np.int64)
        self._pool = np.empty((0, TILE, TILE), dtype=np.int16)
        self._tiles = 0
        self._index = np.full((0, 0), -1, dtype=np.int32)  # tile (ty, tx) → pool slot
        self._index_t0 = np.zeros(2, dtype=np.int64)       # tile (tx, ty) of _index[0, 0]
        self._l_hit = _q(logit(params.p_hit))
        self._l_miss = _q(logit(params.p_miss))
        self._l_min = _q(logit(params.p_min))
        self._l_max = _q(logit(params.p_max))
        self._free_q = _q(logit(params.free_below))
        self._occ_q = _q(logit(params.occupied_above))
        if shape_hw[0] * shape_hw[1]:
            self._cover_tiles()

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state["_pool"] = self._pool[:self._tiles].copy()   # not the spare capacity
        return state

    # -- extent --------------------------------------------------------------------------

    @classmethod
    def covering(cls, params: GridParams, lo_xy: F64, hi_xy: F64) -> OccupancyGrid:
        """An empty grid covering the box [lo, hi] plus the padding, aligned to the resolution."""
        res = params.resolution_m
        lo = np.floor((np.asarray(lo_xy) - params.padding_m) / res) * res
        hi = np.asarray(hi_xy) + params.padding_m
        w, h = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
        return cls(params, (float(lo[0]), float(lo[1])), (max(h, 1), max(w, 1)))

    @classmethod
    def from_dense(cls, params: GridParams, origin_xy: tuple[float, float],
                   log_odds: NDArray[np.floating], observed: NDArray[np.bool_]
                   ) -> OccupancyGrid:
        """A grid holding the given dense log-odds where ``observed`` (clamped, quantised)."""
        lo = np.asarray(log_odds, dtype=np.float64)
        grid = cls(params, origin_xy, (int(lo.shape[0]), int(lo.shape[1])))
        iy, ix = np.nonzero(np.asarray(observed, dtype=bool))
        if len(iy):
            q = np.clip(np.rint(lo[iy, ix] * SCALE), grid._l_min, grid._l_max).astype(np.int16)
            flat = grid._slots(ix, iy)
            grid._pool.reshape(-1)[flat] = q
        return grid

    @property
    def origin(self) -> F64:
        return self._anchor + self._ext[:2].astype(np.float64) * self.resolution_m

    @property
    def origin_pose(self) -> tuple[float, float, float]:
        """nav2 ``origin``: world (x, y, θ = 0) of the lower-left corner of cell (0, 0)."""
        o = self.origin
        return (float(o[0]), float(o[1]), 0.0)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self._ext[3]), int(self._ext[2]))

    @property
    def tiles(self) -> int:
        """Tiles allocated so far."""
        return self._tiles

    @property
    def nbytes(self) -> int:
        """Memory the cells take (allocated tiles and the tile index)."""
        return int(self._tiles * TILE * TILE * 2 + self._index.nbytes)

    def _lattice(self, xy: F64) -> NDArray[np.int64]:
        return np.floor((np.asarray(xy, dtype=np.float64) - self._anchor)
                        / self.resolution_m).astype(np.int64)

    def cell_of(self, xy: F64) -> NDArray[np.int64]:
        """(N, 2) integer (ix, iy) of world points."""
        return self._lattice(xy) - self._ext[:2]

    def ensure_contains(self, lo_xy: F64, hi_xy: F64) -> None:
        """Grow the extent (keeping content) so that the box [lo, hi] lies inside the grid."""
        res = self.resolution_m
        h, w = self.shape
        pad = self.params.padding_m
        lo_xy, hi_xy = np.asarray(lo_xy, dtype=np.float64), np.asarray(hi_xy, dtype=np.float64)
        if h * w == 0:
            fresh = OccupancyGrid.covering(self.params, lo_xy, hi_xy)
            c0 = np.rint((fresh.origin - self._anchor) / res).astype(np.int64)
            self._ext = np.array([c0[0], c0[1], fresh.shape[1], fresh.shape[0]], dtype=np.int64)
            self._cover_tiles()
            return
        origin = self.origin
        hi_grid = origin + np.array([w, h]) * res
        if np.all(lo_xy >= origin) and np.all(hi_xy < hi_grid):
            return
        new_lo = np.minimum(origin, np.floor((lo_xy - pad) / res) * res)
        new_hi = np.maximum(hi_grid, hi_xy + pad)
        nw, nh = (np.ceil((new_hi - new_lo) / res).astype(int) + 1).tolist()
        c0 = self._ext[:2] - np.rint((origin - new_lo) / res).astype(np.int64)
        self._ext = np.array([c0[0], c0[1], nw, nh], dtype=np.int64)
        self._cover_tiles()

    def _cover_tiles(self) -> None:
        """Widen the tile index to the extent's tiles (no tile is allocated here)."""
        x0, y0, w, h = self._ext.tolist()
        t0 = np.array([x0 // TILE, y0 // TILE], dtype=np.int64)
        t1 = np.array([(x0 + max(w, 1) - 1) // TILE, (y0 + max(h, 1) - 1) // TILE]) + 1
        ih, iw = self._index.shape
        t_end = self._index_t0 + np.array([iw, ih])
        if iw and np.all(t0 >= self._index_t0) and np.all(t1 <= t_end):
            return
        if iw:
            t0 = np.minimum(t0, self._index_t0)
            t1 = np.maximum(t1, t_end)
        index = np.full((int(t1[1] - t0[1]), int(t1[0] - t0[0])), -1, dtype=np.int32)
        if iw:
            ox, oy = (self._index_t0 - t0).tolist()
            index[oy:oy + ih, ox:ox + iw] = self._index
        self._index, self._index_t0 = index, t0

    def _slots(self, ix: NDArray[np.int64], iy: NDArray[np.int64]) -> NDArray[np.int64]:
        """Flat pool positions of extent cells (ix, iy), allocating the tiles they fall in."""
        return self._slots_lattice(ix + self._ext[0], iy + self._ext[1])

    def _slots_lattice(self, gx: NDArray[np.int64], gy: NDArray[np.int64]
                       ) -> NDArray[np.int64]:
        """``_slots`` of lattice cells (shifts and masks: TILE is a power of two), allocating
        the tiles they fall in that have none yet (in the order of their index)."""
        gx = np.ascontiguousarray(gx, dtype=np.int64)
        gy = np.ascontiguousarray(gy, dtype=np.int64)
        t0x, t0y = self._index_t0.tolist()
        out, tile, missing = lattice_slots(gx, gy, self._index, t0x, t0y, _TILE_BITS)
        if missing:
            new = np.unique(tile[out < 0])
            self._allocate(len(new))
            self._index.reshape(-1)[new] = np.arange(self._tiles - len(new), self._tiles)
            out, _, _ = lattice_slots(gx, gy, self._index, t0x, t0y, _TILE_BITS)
        return out

    def _allocate(self, n: int) -> None:
        need = self._tiles + n
        if need > len(self._pool):
            grown = np.empty((max(need, 2 * len(self._pool), 16), TILE, TILE), dtype=np.int16)
            grown[:self._tiles] = self._pool[:self._tiles]
            self._pool = grown
        self._pool[self._tiles:need] = UNKNOWN_Q
        self._tiles = need

    # -- updates ---------------------------------------------------------------------------

    def insert_scan(self, T_world_sensor: F64, hits_sensor: Points,
                    misses_sensor: Points | None = None) -> None:
        """Update with one scan: ``hits_sensor`` (N, 2) endpoints in the sensor frame;
        ``misses_sensor`` (M, 2) optional points of beams without a return, only cleared to.
        Returns beyond ``max_ray_m`` only clear their beam up to that range."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        c, s = math.cos(T[2]), math.sin(T[2])
        R = np.array([[c, -s], [s, c]])
        hits = np.asarray(hits_sensor, dtype=np.float64).reshape(-1, 2)
        max_ray = self.params.max_ray_m
        far = np.hypot(hits[:, 0], hits[:, 1]) > max_ray
        ends = hits[~far] @ R.T + T[:2]
        parts = [ends]
        if far.any():
            parts.append(hits[far] @ R.T + T[:2])
        if misses_sensor is not None and len(misses_sensor):
            parts.append(np.asarray(misses_sensor, dtype=np.float64).reshape(-1, 2) @ R.T + T[:2])
        rays = np.concatenate(parts) if len(parts) > 1 else ends
        if len(rays) == 0:
            return
        # clip free-space rays to max_ray_m
        vec = rays - T[:2]
        length = np.hypot(vec[:, 0], vec[:, 1])
        scale = np.minimum(1.0, max_ray / np.maximum(length, 1e-9))
        rays = T[:2] + vec * scale[:, None]
        lo = np.minimum(rays.min(axis=0), T[:2])
        hi = np.maximum(rays.max(axis=0), T[:2])
        self.ensure_contains(lo, hi)
        res = self.resolution_m
        # sample each ray every 0.7 cell (a ray crossing a cell's corner may skip it; other
        # rays and scans fill it), stopping short of its end cell
        step = 0.7 * res
        lengths = length * scale
        n_samp = np.ceil(lengths / step).astype(np.int64)
        gx, gy = ray_cells(float(T[0]), float(T[1]), np.ascontiguousarray(rays), lengths,
                           n_samp, step, float(self._anchor[0]), float(self._anchor[1]), res)
        free = self._slots_lattice(gx, gy)
        hit_cells = self._lattice(ends)
        hit = self._slots_lattice(np.ascontiguousarray(hit_cells[:, 0]),
                                  np.ascontiguousarray(hit_cells[:, 1]))
        # a cell is updated once per scan however many rays cross it, and endpoints are not
        # freed (``grid_kernel.update_cells``)
        update_cells(self._pool.reshape(-1), free, hit, self._l_miss, self._l_min,
                     self._l_hit, self._l_max, int(UNKNOWN_Q), int(_MARK_Q))

    # -- reading ---------------------------------------------------------------------------

    def _dense_rows(self, r0: int, r1: int) -> I16:
        """Quantised log-odds of extent rows [r0, r1) (UNKNOWN_Q where unobserved)."""
        x0, y0, w, _ = self._ext.tolist()
        out = np.full((max(r1 - r0, 0), w), UNKNOWN_Q, dtype=np.int16)
        if r1 <= r0 or w == 0 or self._tiles == 0:
            return out
        gy0, gy1 = y0 + r0, y0 + r1
        tx0, ty0 = self._index_t0.tolist()
        for ty in range(gy0 // TILE, (gy1 - 1) // TILE + 1):
            row = self._index[ty - ty0]
            a, b = max(gy0, ty * TILE), min(gy1, (ty + 1) * TILE)
            for j in np.nonzero(row >= 0)[0].tolist():
                cx0 = (tx0 + j) * TILE
                c0, c1 = max(x0, cx0), min(x0 + w, cx0 + TILE)
                if c1 <= c0:
                    continue
                out[a - gy0:b - gy0, c0 - x0:c1 - x0] = \
                    self._pool[row[j], a - ty * TILE:b - ty * TILE, c0 - cx0:c1 - cx0]
        return out

    def quantised(self) -> I16:
        """Dense int16 log-odds in thousandths (H, W), ``UNKNOWN_Q`` where unobserved."""
        return self._dense_rows(0, self.shape[0])

    def bands(self, rows: int = TILE, top_first: bool = False) -> Iterator[tuple[int, I16]]:
        """The map a strip of ``rows`` rows at a time, (first row, int16 strip), from row 0 up
        (or from the last strip down with ``top_first``; each strip's rows stay in order)."""
        h = self.shape[0]
        starts = list(range(0, h, rows))
        for r0 in reversed(starts) if top_first else starts:
            yield r0, self._dense_rows(r0, min(h, r0 + rows))

    @property
    def log_odds(self) -> NDArray[np.float32]:
        q = self.quantised()
        out = np.where(q == UNKNOWN_Q, 0.0, q / SCALE).astype(np.float32)
        out.setflags(write=False)
        return out

    @property
    def observed(self) -> NDArray[np.bool_]:
        out = self.quantised() != UNKNOWN_Q
        out.setflags(write=False)
        return out

    def probability(self) -> NDArray[np.float32]:
        """Occupancy probability per cell (0.5 where unobserved)."""
        return (1.0 / (1.0 + np.exp(-self.log_odds))).astype(np.float32)

    def to_nav2(self) -> NDArray[np.int8]:
        """int8 (H, W): −1 unknown, else occupancy in percent (0..100)."""
        return self.nav2_of(self.quantised())

    @staticmethod
    def nav2_of(q: I16) -> NDArray[np.int8]:
        """``to_nav2`` of a strip of quantised log-odds: looked up in ``_NAV2`` by the cells'
        16 bits, not computed cell by cell."""
        q = np.ascontiguousarray(q, dtype=np.int16)
        out = np.empty(q.shape, dtype=np.int8)
        _lookup(q.reshape(-1), _NAV2, out.reshape(-1))
        return out

    def free_of(self, q: I16) -> NDArray[np.bool_]:
        """``free_mask`` of a strip of quantised log-odds."""
        return (q != UNKNOWN_Q) & (q < self._free_q)

    def occupied_of(self, q: I16) -> NDArray[np.bool_]:
        """``occupied_mask`` of a strip of quantised log-odds."""
        return q > self._occ_q

    def free_mask(self) -> NDArray[np.bool_]:
        return self.free_of(self.quantised())

    def occupied_mask(self) -> NDArray[np.bool_]:
        return self.occupied_of(self.quantised())


def nav2_formula(q: I16) -> NDArray[np.int8]:
    """nav2 occupancy (−1 unknown, else percent) of quantised log-odds, cell by cell."""
    p = 1.0 / (1.0 + np.exp(-(q.astype(np.float32) / np.float32(SCALE))))
    pct = np.rint(p * OCCUPIED).astype(np.int8)
    return np.where(q == UNKNOWN_Q, np.int8(UNKNOWN), pct).astype(np.int8)


#: ``nav2_formula`` of every int16, indexed by its bits as uint16 (64 KiB, once per process)
_NAV2 = nav2_formula(np.arange(1 << 16, dtype=np.uint16).view(np.int16))
_NAV2.setflags(write=False)


@njit_cached
def _lookup(q: I16, table: NDArray[np.int8], out: NDArray[np.int8]) -> None:
    for i in range(q.size):
        out[i] = table[np.uint16(q[i])]


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    OccupancyGrid.nav2_of(np.array([[UNKNOWN_Q, 0]], dtype=np.int16))
    OccupancyGrid(GridParams()).insert_scan(np.zeros(3), np.array([[1.0, 0.0]]))


_warm_up()
