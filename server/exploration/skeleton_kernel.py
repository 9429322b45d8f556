"""The Voronoi skeleton's ridge marking, compiled (numba): one pass over the cells instead of
four shifted copies of the feature transform."""

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


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    near = np.zeros((2, 2, 2), dtype=np.intp)
    ridge_cells(np.ones((2, 2), np.bool_), near[0], near[1], 1.0, np.zeros((2, 2), np.bool_))


_warm_up()
