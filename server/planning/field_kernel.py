"""Dijkstra from one cell over an 8-connected cost grid, compiled (numba).

The edge cost is the one A* uses (``server.planning.astar_kernel``): the step's length (1 or
√2 cells) times the mean of the two cells' costs, added to the cumulative cost in the same
order, so every settled cell's cost is the same float as scikit-image's ``MCP_Geometric``
gives (``tests/test_field_kernel.py`` checks it bit for bit). Where two paths tie exactly,
the step kept may differ from MCP's: its heap breaks ties another way.

The open list is a binary heap of (cost, cell) pairs, least first, ties by the cell's index,
that knows where each cell sits in it: an improved cell moves up in place (decrease-key), so
each cell enters once. A search given end cells stops once all of them are settled; cells
still in the heap then hold a cost that may not be their least, as with MCP.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached
from server.planning.astar_kernel import SQRT2, _less

#: the eight steps (row, column), in the order MCP_Geometric lists its offsets; a cell's
#: traceback value indexes this table (-1: the start, or not reached)
OFFSETS = np.array([[-1, -1], [-1, 0], [-1, 1], [0, -1], [0, 1], [1, -1], [1, 0], [1, 1]],
                   dtype=np.int64)
#: a cell's place in the heap before it enters and after it is settled
NEW, SETTLED = -1, -2


def cost_field(cost: NDArray[np.float64], start_rc: tuple[int, int],
               ends_rc: list[tuple[int, int]] | None = None
               ) -> tuple[NDArray[np.float64], NDArray[np.int16]]:
    """Least cumulative costs from ``start_rc`` (its own cost not counted) to the cells of
    ``cost`` (H, W; ``inf`` marks a lethal cell), and each cell's traceback index into
    OFFSETS; with ``ends_rc``, until those cells are settled. Unreached cells: ``inf``, -1."""
    H, W = cost.shape
    W2 = W + 2
    padded = np.full((H + 2, W2), np.inf)      # a lethal border: no bounds checks inside
    padded[1:-1, 1:-1] = cost
    flat = padded.ravel()
    n = flat.size
    cum = np.full(n, np.inf)
    back = np.full(n, -1, dtype=np.int16)
    ends = np.zeros(n, dtype=np.uint8)
    n_ends = 0
    for r, c in ends_rc or ():
        i = (r + 1) * W2 + c + 1
        if not ends[i]:
            ends[i] = 1
            n_ends += 1
    where = np.full(n, NEW, dtype=np.int64)   # each cell's place in the heap
    heap_f = np.empty(n)
    heap_v = np.empty(n, dtype=np.int64)
    _search(flat, W2, (start_rc[0] + 1) * W2 + start_rc[1] + 1, ends, n_ends, cum, back,
            where, heap_f, heap_v)
    return (np.ascontiguousarray(cum.reshape(H + 2, W2)[1:-1, 1:-1]),
            np.ascontiguousarray(back.reshape(H + 2, W2)[1:-1, 1:-1]))


@njit_cached
def _put(hf: NDArray[np.float64], hv: NDArray[np.int64], where: NDArray[np.int64], i: int,
         f: float, v: int) -> None:
    hf[i], hv[i] = f, v
    where[v] = i


@njit_cached
def _up(hf: NDArray[np.float64], hv: NDArray[np.int64], where: NDArray[np.int64], i: int,
        f: float, v: int) -> None:
    """Put (f, v) at place ``i`` or above, moving greater parents down."""
    while i > 0:
        p = (i - 1) >> 1
        if not _less(f, v, hf[p], hv[p]):
            break
        _put(hf, hv, where, i, hf[p], hv[p])
        i = p
    _put(hf, hv, where, i, f, v)


@njit_cached
def _down(hf: NDArray[np.float64], hv: NDArray[np.int64], where: NDArray[np.int64], n: int,
          f: float, v: int) -> None:
    """Put (f, v) at the root or below, moving lesser children up (a heap of ``n``)."""
    i = 0
    ch = 1
    while ch < n:
        if ch + 1 < n and _less(hf[ch + 1], hv[ch + 1], hf[ch], hv[ch]):
            ch += 1
        if not _less(hf[ch], hv[ch], f, v):
            break
        _put(hf, hv, where, i, hf[ch], hv[ch])
        i, ch = ch, 2 * ch + 1
    _put(hf, hv, where, i, f, v)


@njit_cached
def _search(c: NDArray[np.float64], w2: int, start: int, ends: NDArray[np.uint8],
            n_ends: int, g: NDArray[np.float64], back: NDArray[np.int16],
            where: NDArray[np.int64], hf: NDArray[np.float64], hv: NDArray[np.int64]) -> None:
    steps = (-w2 - 1, -w2, -w2 + 1, -1, 1, w2 - 1, w2, w2 + 1)
    g[start] = 0.0
    hf[0], hv[0], where[start] = 0.0, start, 0
    n = 1
    left = n_ends
    while n > 0:
        u, gu = hv[0], hf[0]
        where[u] = SETTLED
        n -= 1
        if n > 0:
            _down(hf, hv, where, n, hf[n], hv[n])
        if left > 0 and ends[u]:
            left -= 1
            if left == 0:
                return
        cu = c[u]
        for k in range(8):
            v = u + steps[k]
            cv = c[v]
            if cv == np.inf or where[v] == SETTLED:
                continue
            step = SQRT2 if (k == 0 or k == 2 or k == 5 or k == 7) else 1.0
            ng = gu + step * 0.5 * (cu + cv)
            if ng < g[v]:
                g[v] = ng
                back[v] = k
                i = where[v]
                if i == NEW:
                    i = n
                    n += 1
                _up(hf, hv, where, i, ng, v)


# compiled (or loaded from numba's cache) now, at import, not in a decision's time
cost_field(np.ones((2, 3)), (0, 0), [(1, 2)])
