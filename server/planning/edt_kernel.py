"""The exact Euclidean distance transform with its feature transform, compiled (numba).

``scipy.ndimage.distance_transform_edt(..., return_indices=True)`` gives, for every cell, the
nearest cell outside the mask and the distance to it; the cost layer needs both, the Voronoi
skeleton the nearest cells. This computes the same thing in the same way (the linear-time
algorithm of Maurer, Qi and Raghavan, 2003: nearest obstacle per column, then per row the lower
envelope of the columns' parabolas) with the same choice among equally near cells (the lower
row in a column, the earlier site of a row's envelope), so its results are scipy's to the bit,
in a fifth of the time on a map window.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached


@njit_cached
def _columns(space: NDArray[np.bool_], fr: NDArray[np.int64], seen: NDArray[np.int64]) -> None:
    """Per column, the row of the nearest obstacle cell in that column (-1: none); ties go
    to the upper (lower-index) one. Swept a row at a time, in memory order."""
    H, W = space.shape
    seen[:] = -1
    for r in range(H):              # the nearest obstacle above (or here)
        for c in range(W):
            if not space[r, c]:
                seen[c] = r
            fr[r, c] = seen[c]
    seen[:] = -1
    for r in range(H - 1, -1, -1):  # below, when strictly nearer
        for c in range(W):
            if not space[r, c]:
                seen[c] = r
            b = seen[c]
            if b >= 0 and (fr[r, c] < 0 or b - r < r - fr[r, c]):
                fr[r, c] = b


@njit_cached
def _rows(fr: NDArray[np.int64], out_r: NDArray[np.int64], out_c: NDArray[np.int64],
          dist: NDArray[np.float64], g: NDArray[np.int64], h: NDArray[np.int64]) -> None:
    """Per row, the lower envelope of the parabolas of its columns' nearest obstacles (site
    columns ``g``, squared row offsets ``h``), then each cell's nearest site on it (ties to the
    earlier site)."""
    H, W = fr.shape
    for r in range(H):
        n = -1                                  # top of the envelope's stack
        for c in range(W):
            f = fr[r, c]
            if f < 0:
                continue
            w = (f - r) * (f - r)
            while n >= 1:
                a, b = g[n] - g[n - 1], c - g[n]
                if (a + b) * h[n] - b * h[n - 1] - a * w - a * b * (a + b) <= 0:
                    break
                n -= 1
            n += 1
            g[n], h[n] = c, w
        if n < 0:
            continue
        k = 0
        for c in range(W):
            d1 = h[k] + (g[k] - c) * (g[k] - c)
            while k < n:
                d2 = h[k + 1] + (g[k + 1] - c) * (g[k + 1] - c)
                if d1 <= d2:
                    break
                d1 = d2
                k += 1
            out_r[r, c], out_c[r, c] = fr[r, g[k]], g[k]
            dist[r, c] = math.sqrt(float(d1))


def edt_with_indices(space: NDArray[np.bool_]
                     ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """``distance_transform_edt(space, return_indices=True)`` for a 2-D mask with at least
    one cell outside it: the distance [cells] of every cell to the nearest cell outside
    ``space`` and that cell's (row, col), as a (2, H, W) array."""
    space = np.ascontiguousarray(space, dtype=np.bool_)
    if space.ndim != 2 or space.all():
        raise ValueError("edt_with_indices needs a 2-D mask with a cell outside it")
    H, W = space.shape
    fr = np.empty((H, W), np.int64)
    g = np.empty(W, np.int64)
    _columns(space, fr, g)
    nearest = np.empty((2, H, W), np.intp)
    dist = np.empty((H, W), np.float64)
    _rows(fr, nearest[0], nearest[1], dist, g, np.empty(W, np.int64))
    return dist, nearest


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    edt_with_indices(np.array([[True, False], [True, True]]))


_warm_up()
