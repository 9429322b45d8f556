"""Where a searching robot goes to tell its placements apart.

A robot whose map fits the known map in several places about as well (rooms alike, mirror-
image wings) is not placed until what it sees tells them apart (``search``). Exploring as on
a new mission, it may go on seeing only what all those places share (the rooms of its own
wing). Instead it is sent where they differ:

1. **What each placement predicts.** Around the robot (``REACH_M``, in its own frame, cells
   of ``CELL_M``) the known map is read as each placement of the latest query puts it: a
   wall, open floor (``CLEAR_M`` from every wall), or nothing known.
2. **Where they differ.** A cell is a wall in one placement's map and open floor in
   another's, and the robot's own map has not seen it yet; specks under ``MIN_CELLS`` cells
   are dropped (walls drawn a few centimetres apart are no difference).
3. **Where to look from.** A cell from which a difference lies within ``VIEW_M`` in a
   straight line not blocked by a wall of the strongest placement's map, the nearest such
   cell by the way there over open floor (the strongest placement's, or the robot's own).
4. **The errand.** The way there as far as the robot's own map knows it is open (at most
   ``STEP_M``): the robot goes there, sees more, and is sent on from there (the placements
   having been matched again meanwhile). None: nothing to tell them apart within reach,
   or no way there through what the robot knows; it explores as it would.

The robot's LIDAR sees all around (360°): turning on the spot shows it nothing new; where it
cannot tell, it drives to where the difference can be seen. No I/O here.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_dilation, distance_transform_edt, label

from server.knownmap.placing import Placement
from server.rendezvous.mapmatch import Layers

F64 = NDArray[np.float64]
B = NDArray[np.bool_]

CELL_M = 0.2          # cells of the comparison (the matching's search resolution)
REACH_M = 20.0        # half the side of the square compared around the robot
CLEAR_M = 0.3         # open floor: this far from every wall of that map
MIN_CELLS = 4         # a difference holds at least this many cells (0.16 m²)
VIEW_M = 4.0          # a difference is seen from this near, in a straight line
STEP_M = 6.0          # an errand goes at most this far along the way
SHARE = 0.5           # placements at least this share of the strongest's strength count
NEAR_M = 0.5          # an errand shorter than this is no errand
GOAL_CLEAR_M = 0.6    # an errand's goal at least this far from the robot's walls
MARGIN = 8            # cells (0.2 m) of contradiction that tell two placements apart


def clear_layer(lay: Layers) -> B:
    """The map's open floor at least ``CLEAR_M`` from its walls (coarse cells)."""
    n = max(1, math.ceil(CLEAR_M / lay.cell_m))
    return lay.free & ~binary_dilation(lay.occ, iterations=n)


def _sample(mask: B, origin: F64, cell_m: float, xy: F64) -> B:
    j = np.floor((xy[:, 0] - origin[0]) / cell_m).astype(np.int64)
    i = np.floor((xy[:, 1] - origin[1]) / cell_m).astype(np.int64)
    h, w = mask.shape
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    out = np.zeros(len(xy), dtype=bool)
    out[ok] = mask[i[ok], j[ok]]
    return out


def _moved(T: F64, xy: F64) -> F64:
    c, s = math.cos(T[2]), math.sin(T[2])
    return np.stack([T[0] + c * xy[:, 0] - s * xy[:, 1], T[1] + s * xy[:, 0] + c * xy[:, 1]],
                    axis=1)


def differences(known: Layers, known_clear: B, own: Layers, Ts: list[F64], centre: F64
                ) -> tuple[B, list[B], list[B], F64]:
    """Step 1 and 2 around ``centre`` (own frame): the cells where the placements ``Ts``
    (own frame -> map) differ, each placement's walls and open floor, and the square's
    corner (own frame)."""
    n = round(2 * REACH_M / CELL_M)
    corner = np.asarray(centre[:2], float) - REACH_M
    c = corner[None, :] + (np.stack(np.meshgrid(np.arange(n), np.arange(n)), axis=-1)
                           .reshape(-1, 2) + 0.5) * CELL_M        # (x, y) of row i, col j
    walls, floor = [], []
    for T in Ts:
        q = _moved(T, c)
        walls.append(_sample(known.occ, known.origin, known.cell_m, q).reshape(n, n))
        floor.append(_sample(known_clear, known.origin, known.cell_m, q).reshape(n, n))
    seen = (_sample(own.occ, own.origin, own.cell_m, c) |
            _sample(own.free, own.origin, own.cell_m, c)).reshape(n, n)
    differ = np.logical_or.reduce(walls) & np.logical_or.reduce(floor) & ~seen
    lab, k = label(differ, structure=np.ones((3, 3), bool))
    if k:
        sizes = np.bincount(lab.ravel())
        differ = sizes[lab] >= MIN_CELLS
        differ[lab == 0] = False
    return differ, walls, floor, corner


def _wavefront(open_: B, start: tuple[int, int]) -> NDArray[np.int64]:
    """Steps (8-connected) from ``start`` over ``open_`` cells; -1 where not reached."""
    dist = np.full(open_.shape, -1, dtype=np.int64)
    front = np.zeros_like(open_)
    front[start] = True
    reached = front.copy()
    k = 0
    while front.any():
        dist[front] = k
        k += 1
        grown = front.copy()        # the front grown by one cell (8 neighbours), by slices
        grown[1:] |= front[:-1]
        grown[:-1] |= front[1:]
        row = grown.copy()
        grown[:, 1:] |= row[:, :-1]
        grown[:, :-1] |= row[:, 1:]
        grown &= open_ & ~reached
        reached |= grown
        front = grown
    return dist


def _line_open(walls: B, a: tuple[int, int], b: tuple[int, int]) -> bool:
    """No wall on the straight line from cell ``a`` to ``b`` (the last cells, on the
    difference itself, not counted)."""
    n = max(abs(b[0] - a[0]), abs(b[1] - a[1]))
    if n <= 2:
        return True
    t = np.arange(n - 1) / n
    i = np.round(a[0] + t * (b[0] - a[0])).astype(np.int64)
    j = np.round(a[1] + t * (b[1] - a[1])).astype(np.int64)
    return not bool(walls[i, j].any())


def errand_goal(known: Layers, known_clear: B, own: Layers, own_clear: B,
                Ts: list[F64], pose: F64) -> tuple[float, float] | None:
    """Where the robot at ``pose`` (own frame) goes to tell the placements ``Ts`` apart
    (the strongest first), in its own frame; None: nowhere (the module docstring)."""
    if len(Ts) < 2:
        return None
    differ, walls, floor, corner = differences(known, known_clear, own, Ts, pose)
    if not differ.any():
        return None
    n = differ.shape[0]
    c = corner[None, :] + (np.stack(np.meshgrid(np.arange(n), np.arange(n)), axis=-1)
                           .reshape(-1, 2) + 0.5) * CELL_M
    mine = _sample(own_clear, own.origin, own.cell_m, c).reshape(n, n)
    own_walls = binary_dilation(_sample(own.occ, own.origin, own.cell_m, c).reshape(n, n))
    start = (n // 2, n // 2)
    open_ = (floor[0] | mine) & ~own_walls
    open_[start] = True
    dist = _wavefront(open_, start)
    gap, (ii, jj) = distance_transform_edt(~differ, return_indices=True)
    view = (dist >= 0) & (gap * CELL_M <= VIEW_M)
    cand = np.argwhere(view)
    order = np.argsort(dist[view], kind="stable")
    target = None
    # walls a line cannot slip through between two cells touching at a corner
    blocking = binary_dilation(walls[0])
    for i, j in cand[order[:400]]:
        if _line_open(blocking, (int(i), int(j)), (int(ii[i, j]), int(jj[i, j]))):
            target = (int(i), int(j))
            break
    if target is None:
        return None
    # the way back from the target to the robot, then the part of it the robot knows open
    path = [target]
    while dist[path[-1]] > 0:
        i, j = path[-1]
        nb = [(a, b) for a in (i - 1, i, i + 1) for b in (j - 1, j, j + 1)
              if 0 <= a < n and 0 <= b < n and dist[a, b] == dist[i, j] - 1]
        path.append(nb[0])
    path.reverse()
    known_open = _sample(own.free, own.origin, own.cell_m, c).reshape(n, n)
    own_occ = _sample(own.occ, own.origin, own.cell_m, c).reshape(n, n)
    # a goal well away from the walls the robot knows (the planner's lethal band around them)
    roomy = mine & (distance_transform_edt(~own_occ) * CELL_M >= GOAL_CLEAR_M)
    goal = None
    for i, j in path[1:]:
        if not known_open[i, j] or math.hypot(i - start[0], j - start[1]) * CELL_M > STEP_M:
            break
        if roomy[i, j]:
            goal = (i, j)
    if goal is None or math.hypot(goal[0] - start[0], goal[1] - start[1]) * CELL_M < NEAR_M:
        return None
    x, y = corner + (np.array([goal[1], goal[0]]) + 0.5) * CELL_M
    return float(x), float(y)


def conflicts(T: F64, own: Layers, own_clear: B, known: Layers, known_clear: B) -> int:
    """Cells where the robot's map (its frame) laid on the known map by ``T`` contradicts
    it: the robot's walls on the map's open floor, and the robot's open floor on the map's
    walls (open floor ``CLEAR_M`` from every wall on both sides: a wall drawn a little off
    is no contradiction)."""
    def centres(mask: B) -> F64:
        ij = np.argwhere(mask)
        return own.origin[None, :] + (ij[:, ::-1] + 0.5) * own.cell_m
    walls_on_floor = _sample(known_clear, known.origin, known.cell_m,
                             _moved(T, centres(own.occ)))
    floor_on_walls = _sample(known.occ, known.origin, known.cell_m,
                             _moved(T, centres(own_clear)))
    return int(walls_on_floor.sum() + floor_on_walls.sum())


def apart(mine: int, other: int) -> bool:
    """A placement the robot's map contradicts in ``other`` cells is told apart from one it
    contradicts in ``mine``: ``MARGIN`` more, and at least twice as many."""
    return other >= mine + MARGIN and other >= 2 * mine


def told_apart(ranked: list[Placement], ratio: float, own: Layers, own_clear: B,
               known: Layers, known_clear: B) -> Placement | None:
    """Among placements about as strong as the strongest (``ratio`` of it or more), the one
    the robot's map contradicts least, when it contradicts every other of them by at least
    ``MARGIN`` cells more and no more than half as much: the robot has seen what tells them
    apart (a wall where the others have open floor, the end of a corridor), though it is
    little beside all they share. None: nothing tells them apart yet."""
    if not ranked or ranked[0].strength <= 0:
        return None
    ties = [pl for pl in ranked if pl.strength >= ratio * ranked[0].strength]
    if len(ties) < 2:
        return None
    c = [conflicts(pl.T_map_own, own, own_clear, known, known_clear) for pl in ties]
    k = int(np.argmin(c))
    if all(apart(c[k], c[i]) for i in range(len(ties)) if i != k):
        return ties[k]
    return None
