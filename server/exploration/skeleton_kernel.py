"""The Voronoi skeleton's ridge marking and thinning, compiled (numba).

``ridge_cells``: one pass over the cells instead of four shifted copies of the feature
transform. ``thin``: Zhang–Suen thinning that looks only at the cells still set, where a
thinning over the whole image visits every cell on every pass; the ridge band is a small share
of the map, so most of those visits found nothing to do.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached


@njit_cached
def ridge_cells(space: NDArray[np.bool_], fr: NDArray[np.intp], fc: NDArray[np.intp],
                tau2: float, out: NDArray[np.bool_]) -> None:
    """Mark in ``out`` each cell of ``space`` that has an 8-neighbour in ``space`` whose
    nearest boundary cell (``fr``, ``fc``) lies at least √``tau2`` cells from its own."""
    H, W = space.shape
    for r in range(H):
        for c in range(W):
            if not space[r, c]:
                continue
            # half of the 8-neighbourhood (E, S, SE, SW): each pair is looked at once
            for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
                r2, c2 = r + dr, c + dc
                if r2 >= H or c2 < 0 or c2 >= W or not space[r2, c2]:
                    continue
                er, ec = fr[r, c] - fr[r2, c2], fc[r, c] - fc[r2, c2]
                if er * er + ec * ec >= tau2:
                    out[r, c] = True
                    out[r2, c2] = True


# The neighbourhoods of a set cell that thinning removes, by the code of the neighbourhood
# (NW 1, N 2, NE 4, E 8, SE 16, S 32, SW 64, W 128): in the first sub-pass only, in the second
# only, or in either. These are the classes of scikit-image's Zhang–Suen thinning
# (``skimage.morphology.skeletonize``), which the skeleton was made with before; the skeleton
# is therefore the same, cell for cell (``tests/test_map_kernels.py`` checks it).
_FIRST_ONLY = (3, 6, 11, 12, 14, 131, 134, 143, 159, 161, 194, 198, 207, 227, 231, 243)
_SECOND_ONLY = (24, 26, 56, 62, 63, 96, 104, 108, 126, 176, 192, 224, 248, 249, 252)
_EITHER = (7, 10, 15, 28, 30, 31, 40, 60, 112, 120, 124, 130, 135, 160, 193, 195, 199, 225,
           240, 241)


def _removal_table() -> NDArray[np.uint8]:
    """Per neighbourhood code: bit 1 set when the first sub-pass removes the cell, bit 2
    when the second does."""
    table = np.zeros(256, np.uint8)
    table[list(_FIRST_ONLY)] = 1
    table[list(_SECOND_ONLY)] = 2
    table[list(_EITHER)] = 3
    return table


REMOVAL = _removal_table()


@njit_cached
def thin(image: NDArray[np.bool_], removal: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Zhang–Suen thinning of ``image`` to one-cell-wide lines (``removal``: the table of
    ``_removal_table``). Each sub-pass judges every set cell on the image as the sub-pass
    found it, then clears those it removes; passes repeat until one removes nothing. The
    order in which cells are judged therefore does not matter, and only set cells are."""
    H, W = image.shape
    sk = np.zeros((H + 2, W + 2), np.uint8)
    n = 0
    for r in range(H):
        for c in range(W):
            if image[r, c]:
                sk[r + 1, c + 1] = 1
                n += 1
    rows = np.empty(n, np.int64)
    cols = np.empty(n, np.int64)
    k = 0
    for r in range(H):
        for c in range(W):
            if image[r, c]:
                rows[k], cols[k] = r + 1, c + 1
                k += 1
    gone = np.zeros(n, np.bool_)
    removed = True
    while removed:
        removed = False
        for sub in range(2):
            bit = 1 << sub
            hit = 0
            for i in range(n):
                r, c = rows[i], cols[i]
                code = (sk[r - 1, c - 1] + 2 * sk[r - 1, c] + 4 * sk[r - 1, c + 1]
                        + 8 * sk[r, c + 1] + 16 * sk[r + 1, c + 1] + 32 * sk[r + 1, c]
                        + 64 * sk[r + 1, c - 1] + 128 * sk[r, c - 1])
                if removal[code] & bit:
                    gone[i] = True
                    hit += 1
            if hit == 0:
                continue
            removed = True
            k = 0
            for i in range(n):
                if gone[i]:
                    sk[rows[i], cols[i]] = 0
                    gone[i] = False
                else:
                    rows[k], cols[k] = rows[i], cols[i]
                    k += 1
            n = k
    out = np.zeros((H, W), np.bool_)
    for i in range(n):
        out[rows[i] - 1, cols[i] - 1] = True
    return out


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    near = np.zeros((2, 2, 2), dtype=np.intp)
    ridge_cells(np.ones((2, 2), np.bool_), near[0], near[1], 1.0, np.zeros((2, 2), np.bool_))
    thin(np.ones((3, 3), np.bool_), REMOVAL)


_warm_up()
