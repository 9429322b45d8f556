"""The occupancy grid's scan update, compiled (numba): ``OccupancyGrid.insert_scan``'s ray
sampling, tile look-up and cell update without the temporary arrays of the numpy steps.

Each step does the numpy version's arithmetic in the same order (IEEE double, no fused
multiply-add), and a cell crossed by several rays of one scan is read once before any is
written, as numpy's assignment through repeated indices does: the grid is the same bit for
bit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
I32 = NDArray[np.int32]
I16 = NDArray[np.int16]


@njit_cached
def ray_cells(tx: float, ty: float, rays: F64, lengths: F64, n_samp: I64, step: float,
              ax: float, ay: float, res: float) -> tuple[I64, I64]:
    """Lattice cells (gx, gy) of the samples every ``step`` along each ray from (tx, ty) to
    ``rays[i]``, ``n_samp[i]`` of them from its start (the ray's end cell not included)."""
    total = 0
    for i in range(len(n_samp)):
        total += n_samp[i]
    gx = np.empty(total, dtype=np.int64)
    gy = np.empty(total, dtype=np.int64)
    j = 0
    for i in range(len(n_samp)):
        length = max(lengths[i], 1e-9)
        dx = rays[i, 0] - tx
        dy = rays[i, 1] - ty
        for k in range(n_samp[i]):
            frac = (float(k) * step) / length
            px = tx + frac * dx
            py = ty + frac * dy
            gx[j] = math.floor((px - ax) / res)
            gy[j] = math.floor((py - ay) / res)
            j += 1
    return gx, gy


@njit_cached
def lattice_slots(gx: I64, gy: I64, index: I32, t0x: int, t0y: int, bits: int
                  ) -> tuple[I64, I64, int]:
    """Flat pool positions of lattice cells (``OccupancyGrid._slots_lattice``), their tiles
    (row-major in ``index``), and how many fall in a tile not allocated yet (their position
    is then -1). IndexError for a cell outside ``index``'s tiles (never written)."""
    n = len(gx)
    ih, iw = index.shape
    flat = index.reshape(-1)
    mask = (1 << bits) - 1
    out = np.empty(n, dtype=np.int64)
    tiles = np.empty(n, dtype=np.int64)
    missing = 0
    for i in range(n):
        tx, ty = (gx[i] >> bits) - t0x, (gy[i] >> bits) - t0y
        if tx < 0 or tx >= iw or ty < 0 or ty >= ih:
            raise IndexError("a cell outside the grid's tiles")
        tile = ty * iw + tx
        tiles[i] = tile
        slot = flat[tile]
        if slot < 0:
            missing += 1
            out[i] = -1
            continue
        out[i] = (np.int64(slot) << (2 * bits)) + ((gy[i] & mask) << bits) + (gx[i] & mask)
    return out, tiles, missing


@njit_cached
def update_cells(pool: I16, free: I64, hit: I64, l_miss: int, l_min: int, l_hit: int,
                 l_max: int, unknown: int, mark: int) -> None:
    """One scan's update of the flat ``pool``: every ``free`` cell that is not a ``hit`` cell
    once by ``l_miss`` (down to ``l_min``), every ``hit`` cell once by ``l_hit`` (up to
    ``l_max``); an ``unknown`` cell starts at 0."""
    kept = np.empty(len(hit), dtype=np.int16)
    for i in range(len(hit)):
        kept[i] = pool[hit[i]]
    for i in range(len(hit)):
        pool[hit[i]] = mark
    new = np.empty(len(free), dtype=np.int16)
    take = np.zeros(len(free), dtype=np.bool_)
    for i in range(len(free)):
        v = int(pool[free[i]])
        if v == mark:
            continue
        if v == unknown:
            v = 0
        new[i] = max(v + l_miss, l_min)
        take[i] = True
    for i in range(len(hit)):
        pool[hit[i]] = kept[i]
    for i in range(len(free)):
        if take[i]:
            pool[free[i]] = new[i]
    for i in range(len(hit)):
        v = int(kept[i])
        if v == unknown:
            v = 0
        kept[i] = min(v + l_hit, l_max)
    for i in range(len(hit)):
        pool[hit[i]] = kept[i]
