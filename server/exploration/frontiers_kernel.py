"""Grouping frontier cells into clusters, compiled (numba): a flood fill over the few frontier
cells instead of labelling, counting and remapping the whole map window."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached
from server.planning.grid_kernel import bordered, fill


@njit_cached
def clusters(mask: NDArray[np.bool_], min_cells: int
             ) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """The cells of ``mask``'s 8-connected components of at least ``min_cells`` cells, as flat
    indices in row-major order, each with its component's number (0, 1, …, in the row-major
    order of the components' first cells, as ``ndimage.label`` numbers them), and the number
    of components kept."""
    H, W = mask.shape
    W2 = W + 2
    left, steps, count = bordered(mask)
    stack = np.empty(count, np.int64)
    label = np.full((H + 2) * W2, -1, np.int64)
    kept = 0
    for r0 in range(H):
        for c0 in range(W):
            p0 = (r0 + 1) * W2 + c0 + 1
            if not left[p0]:
                continue
            n = fill(left, steps, stack, p0)
            if n >= min_cells:
                for i in range(n):
                    label[stack[i]] = kept
                kept += 1
    flat = np.empty(count, np.int64)
    cluster = np.empty(count, np.int64)
    m = 0
    for r in range(H):
        for c in range(W):
            lab = label[(r + 1) * W2 + c + 1]
            if lab >= 0:
                flat[m], cluster[m] = r * W + c, lab
                m += 1
    return flat[:m], cluster[:m], kept


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    clusters(np.ones((2, 2), np.bool_), 1)


_warm_up()
