"""A*'s inner loop, compiled (numba): the same expansions, in the same order, as a Python loop
over ``heapq`` would make, at a small fraction of the cost.

The open list is a binary heap of (f, cell) pairs kept exactly as ``heapq`` keeps a list of
tuples (the same sift-down and sift-up, pairs compared first by f, then by cell), so ties are
broken the same way and a path found here is the one the reference loop finds. The search runs
in slices of a given number of expansions; between slices the caller may check the clock, and
the state (g, parents, closed set, heap) carries over.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached

SQRT2 = float(np.sqrt(2.0))

#: what a slice ends with: the goal reached, no path, or the slice's expansions used up
FOUND, NO_PATH, GOING = 0, 1, 2


class Search:
    """One A* search's state over a padded cost array (a lethal border of one cell)."""

    def __init__(self, padded: NDArray[np.float64], start: int, goal: int, min_cost: float,
                 check_every: int) -> None:
        n = padded.size
        self.cost = padded.ravel()
        self.width = padded.shape[1]
        self.goal, self.min_cost, self.check_every = goal, min_cost, check_every
        self.g = np.full(n, np.inf)
        self.parent = np.full(n, -1, dtype=np.int64)
        self.closed = np.zeros(n, dtype=np.uint8)
        # every relaxation pushes once: at most 8 per cell, and the start
        self.heap_f = np.empty(8 * n + 1)
        self.heap_v = np.empty(8 * n + 1, dtype=np.int64)
        self.g[start] = 0.0
        self.heap_f[0], self.heap_v[0] = 0.0, start
        #: heap size, cells expanded, the cell closed and not yet expanded when a slice ended
        self.state = np.array([1, 0, -1], dtype=np.int64)

    def run(self) -> int:
        """Search on to the goal, to the end, or to the next clock check (every
        ``check_every`` expansions from the first, as the reference loop checks): FOUND,
        NO_PATH or GOING."""
        return int(_search(self.cost, self.width, self.goal, self.min_cost, self.g,
                           self.parent, self.closed, self.heap_f, self.heap_v, self.state,
                           self.check_every))

    @property
    def expanded(self) -> int:
        return int(self.state[1])


@njit_cached
def _less(fa: float, va: int, fb: float, vb: int) -> bool:
    return fa < fb or (fa == fb and va < vb)


@njit_cached
def _sift_down(hf: NDArray[np.float64], hv: NDArray[np.int64], start: int, pos: int) -> None:
    nf, nv = hf[pos], hv[pos]
    while pos > start:
        parent = (pos - 1) >> 1
        if _less(nf, nv, hf[parent], hv[parent]):
            hf[pos], hv[pos] = hf[parent], hv[parent]
            pos = parent
            continue
        break
    hf[pos], hv[pos] = nf, nv


@njit_cached
def _sift_up(hf: NDArray[np.float64], hv: NDArray[np.int64], pos: int, end: int) -> None:
    start = pos
    nf, nv = hf[pos], hv[pos]
    child = 2 * pos + 1
    while child < end:
        right = child + 1
        if right < end and not _less(hf[child], hv[child], hf[right], hv[right]):
            child = right
        hf[pos], hv[pos] = hf[child], hv[child]
        pos = child
        child = 2 * pos + 1
    hf[pos], hv[pos] = nf, nv
    _sift_down(hf, hv, start, pos)


@njit_cached
def _expand(u: int, c: NDArray[np.float64], w2: int, gr: int, gc: int, min_cost: float,
            g: NDArray[np.float64], parent: NDArray[np.int64], closed: NDArray[np.uint8],
            hf: NDArray[np.float64], hv: NDArray[np.int64], n: int) -> int:
    """Relax ``u``'s eight neighbours, pushing each improved one; the heap's new size."""
    diag = SQRT2 - 1.0
    gu, cu = g[u], c[u]
    for k in range(8):
        if k == 0:
            off, step = 1, 1.0
        elif k == 1:
            off, step = -1, 1.0
        elif k == 2:
            off, step = w2, 1.0
        elif k == 3:
            off, step = -w2, 1.0
        elif k == 4:
            off, step = w2 + 1, SQRT2
        elif k == 5:
            off, step = w2 - 1, SQRT2
        elif k == 6:
            off, step = -w2 + 1, SQRT2
        else:
            off, step = -w2 - 1, SQRT2
        v = u + off
        cv = c[v]
        if cv == np.inf or closed[v]:
            continue
        ng = gu + step * 0.5 * (cu + cv)
        if ng < g[v]:
            g[v] = ng
            parent[v] = u
            vr, vc = v // w2, v % w2
            dr, dc = abs(vr - gr), abs(vc - gc)
            m = min(dr, dc)
            h = ((dr + dc) + diag * m - m) * min_cost
            hf[n], hv[n] = ng + h, v
            _sift_down(hf, hv, 0, n)
            n += 1
    return n


@njit_cached
def _search(c: NDArray[np.float64], w2: int, goal: int, min_cost: float,
            g: NDArray[np.float64], parent: NDArray[np.int64], closed: NDArray[np.uint8],
            hf: NDArray[np.float64], hv: NDArray[np.int64], state: NDArray[np.int64],
            check_every: int) -> int:
    gr, gc = goal // w2, goal % w2
    n = state[0]
    if state[2] >= 0:                  # the cell the last slice closed: expand it now
        n = _expand(state[2], c, w2, gr, gc, min_cost, g, parent, closed, hf, hv, n)
        state[2] = -1
    while n > 0:
        # pop the least pair, as heapq.heappop does
        n -= 1
        lf, lv = hf[n], hv[n]
        if n > 0:
            u = hv[0]
            hf[0], hv[0] = lf, lv
            _sift_up(hf, hv, 0, n)
        else:
            u = lv
        if closed[u]:
            continue
        if u == goal:
            state[0] = n
            return FOUND
        closed[u] = 1
        state[1] += 1
        if state[1] % check_every == 1:   # the caller looks at the clock here
            state[0], state[2] = n, u
            return GOING
        n = _expand(u, c, w2, gr, gc, min_cost, g, parent, closed, hf, hv, n)
    state[0] = 0
    return NO_PATH


def _warm_up() -> None:
    """Compile (or load the compiled code from numba's cache) now, at import, so that no
    search's clock includes the compiling."""
    padded = np.full((3, 4), np.inf)
    padded[1, 1:3] = 1.0
    Search(padded, 5, 6, 1.0, 2048).run()


_warm_up()
