"""Loop closure's path lengths over the keyframe graph, compiled (numba): the relaxation of
``_Graph.distances_from`` without a numpy call per edge. The same additions, comparisons
and minima in the same order as the loop it replaced: the same distances, bit for bit."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from server.jit import njit_cached

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@njit_cached
def relax(arc: F64, source: int, ea: I64, eb: I64, ew: F64) -> F64:
    """Path lengths from keyframe ``source`` along the chain (``arc``: cumulative length)
    and the shortcut edges (``ea``, ``eb``, ``ew``), relaxed until nothing changes (at most
    once per edge and once more)."""
    m = len(arc)
    d = np.empty(m)
    for i in range(m):
        d[i] = abs(arc[i] - arc[source])
    for _ in range(len(ea) + 1):
        changed = False
        for e in range(len(ea)):
            for side in range(2):
                u, v = (ea[e], eb[e]) if side == 0 else (eb[e], ea[e])
                via = d[u] + ew[e]
                if via < d[v] - 1e-9:
                    for i in range(m):
                        x = via + abs(arc[i] - arc[v])
                        if x < d[i]:
                            d[i] = x
                    changed = True
        if not changed:
            break
    return d


relax(np.zeros(2), 0, np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64), np.ones(1))


# compiled now, at import, not at the first loop closure (see ``server.slam.icp._warm_up``)
relax(np.array([0.0, 1.0, 2.0]), 0, np.array([0], dtype=np.int64),
      np.array([2], dtype=np.int64), np.array([0.5]))
