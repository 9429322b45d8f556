"""Finding the small pockets of a mask, compiled (numba): one flood fill over the mask's
8-connected components, instead of labelling the whole array and counting every label."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached


@njit_cached
def bordered(mask: NDArray[np.bool_]) -> tuple[NDArray[np.uint8], NDArray[np.int64], int]:
    """``mask`` flattened with a border of zeros (the cells ``fill`` is to reach, row r and
    column c at ``(r + 1) * (W + 2) + c + 1``), the 8 neighbours' offsets in it, and the number
    of cells set."""
    H, W = mask.shape
    W2 = W + 2
    left = np.zeros((H + 2) * W2, np.uint8)
    count = 0
    for r in range(H):
        for c in range(W):
            if mask[r, c]:
                left[(r + 1) * W2 + c + 1] = 1
                count += 1
    steps = np.array([-W2 - 1, -W2, -W2 + 1, -1, 1, W2 - 1, W2, W2 + 1], np.int64)
    return left, steps, count


@njit_cached
def fill(left: NDArray[np.uint8], steps: NDArray[np.int64], stack: NDArray[np.int64],
         p0: int) -> int:
    """Flood-fill the 8-connected component of flat cell ``p0`` in ``left`` (cells not yet
    reached, with a border of zeros; ``steps`` the 8 neighbours' offsets): clears its cells in
    ``left`` and leaves them in ``stack[0:n]`` in the order reached; returns ``n``."""
    left[p0] = 0
    stack[0] = p0
    top, n = 1, 0
    while n < top:
        p = stack[n]
        n += 1
        for k in range(8):
            q = p + steps[k]
            if left[q]:
                left[q] = 0
                stack[top] = q
                top += 1
    return n


@njit_cached
def small_pockets(mask: NDArray[np.bool_], max_cells: int, out: NDArray[np.bool_]) -> None:
    """Set in ``out`` the cells of the 8-connected components of ``mask`` with at most
    ``max_cells`` cells that touch no border of the array."""
    H, W = mask.shape
    W2 = W + 2
    left, steps, _ = bordered(mask)
    stack = np.empty(H * W, np.int64)
    for r0 in range(H):
        for c0 in range(W):
            p0 = (r0 + 1) * W2 + c0 + 1
            if not left[p0]:
                continue
            n = fill(left, steps, stack, p0)
            if n > max_cells:
                continue
            border = False
            for i in range(n):
                r, c = stack[i] // W2 - 1, stack[i] % W2 - 1
                if r == 0 or c == 0 or r == H - 1 or c == W - 1:
                    border = True
            if not border:
                for i in range(n):
                    out[stack[i] // W2 - 1, stack[i] % W2 - 1] = True


def _warm_up() -> None:
    """Compile (or load from numba's cache) at import, not in a scan's time."""
    small_pockets(np.ones((3, 3), np.bool_), 1, np.zeros((3, 3), np.bool_))


_warm_up()
