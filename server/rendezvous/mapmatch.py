"""Where one team's map lies in another's, from the maps alone: candidates, then consistency.

Two teams that have not met may already have mapped the same rooms. This module finds the
transforms (b's team frame -> a's) under which parts of one map fit the other, and says when
they agree well enough to merge without a meeting. Three steps:

1. **Rotations from wall directions.** Each map's Hough spectrum (for every line direction,
   the sum of the squared votes over all offsets: large where many cells lie on few long
   lines) is taken over 180°. The circular cross-correlation of two spectra peaks at the
   rotations that bring one map's wall directions onto the other's; in a building with
   square corners that is four rotations 90° apart. Only narrow windows around those peaks
   (and their half-turns) are searched, so a query is cheap.
2. **Candidates per submap.** A submap is the part of one map within a square around one of
   its robots' keyframes; submaps are taken at places far apart. For each rotation, every
   translation is scored at once by FFT correlation: walls of the submap on walls of the
   other map count for it, walls of either in the other's open space against it. The best
   peaks over all rotations, refined on the fine grid, are scored by the acceptance index
   (Birk and Carpin): cells on which both maps agree (occupied on occupied, free on free)
   over those plus the cells on which they disagree, in the overlap only. The top
   ``top_k`` of each submap are kept, not just the best: in a building of similar rooms,
   the best single score is often wrong.
3. **Consistency.** Candidates from different submaps that imply the same transform support
   each other (pairwise consistency, as in Mangelson et al. 2018). The largest set of
   mutually consistent candidates, counted in distinct places, is the hypothesis. It is
   accepted only when it has ``min_support`` places, ``min_distinct`` of them distinct (the
   submap fits there clearly better than at its next best place: in a building of repeated
   rooms a submap fits several places about equally), and clearly dominates the best set
   that contradicts it (``dominance``). A hypothesis short of that can be settled by meeting.

This module holds the types, the layers and the consistency (step 3); ``server.rendezvous.
submaps`` the rotations, the candidates (steps 1 and 2) and a query of one pair
(``match_pair``). No I/O and no server state here: ``match_pair`` takes two grids and keyframe
positions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose, inverse, transform_points, wrap_angle
from server.slam.grid import OccupancyGrid

F64 = NDArray[np.float64]
B = NDArray[np.bool_]


@dataclass(frozen=True)
class MatchParams:
    cell_m: float = 0.2             # search resolution (the grid's, coarsened by a whole factor)
    submap_m: float = 10.0          # side of a submap's square
    spacing_m: float = 5.0          # submap centres at least this far apart
    max_submaps: int = 8            # per side and query of a pair, the best-walled first
    min_submap_walls: int = 50      # wall cells (search resolution) for a submap to be matched
    window_deg: float = 1.0         # searched around each rotation peak ...
    step_deg: float = 1.0           # ... in these steps
    max_rotation_peaks: int = 4     # of the spectra's correlation, in [0°, 180°)
    conflict_weight: float = 2.0    # a wall in open space counts against this many hits
    top_k: int = 3                  # candidates kept per submap
    min_hits: int = 40              # wall cells of the submap on walls (search resolution)
    min_acceptance: float = 0.9     # Birk and Carpin's index over the overlap
    peak_separation_m: float = 1.5  # candidates of one submap at least this far apart
    consistent_m: float = 0.6       # two candidates agree: positions within this ...
    consistent_deg: float = 2.5     # ... and rotations within this
    min_support: int = 3            # distinct places for a hypothesis to be accepted ...
    min_side_support: int = 2       # ... with this many submaps of each map among them
    dominance: float = 2.0          # its support over that of the best contradicting set
    distinct_ratio: float = 0.8     # a submap's next best placement scores at most this much
    min_distinct: int = 2           # ... at this many of the places


@dataclass(frozen=True)
class Candidate:
    """Submap ``submap`` (of side ``side``: "a" or "b") fits the other map under ``T_ab``."""

    T_ab: F64                 # b's team frame -> a's
    side: str
    submap: int
    centre_a: F64             # the submap's centre in a's frame (under T_ab)
    score: float              # hits − weight · conflicts (search resolution)
    hits: int
    conflicts: int
    acceptance: float         # agreement / (agreement + disagreement), fine grid
    overlap_cells: int        # known in both (fine grid)


@dataclass(frozen=True)
class Hypothesis:
    T_ab: F64
    support: int              # distinct places whose submaps agree on T_ab
    members: tuple[Candidate, ...]
    rival_support: int        # of the best set contradicting it
    acceptance: float         # mean over members
    distinct: int = 0         # places whose submap fits there clearly better than elsewhere

    def side_support(self, side: str) -> int:
        return sum(1 for c in self.members if c.side == side)

    def accepted(self, p: MatchParams) -> bool:
        """Enough places, seen from both maps (a true overlap is found whichever map the
        submap is cut from; a wrong fit of one map's walls seldom works the other way too),
        and clearly more than any contradicting set."""
        return self.support >= p.min_support and self.distinct >= p.min_distinct and \
            min(self.side_support("a"), self.side_support("b")) >= p.min_side_support and \
            self.support >= p.dominance * max(self.rival_support, 1)


@dataclass
class PairResult:
    candidates: list[Candidate] = field(default_factory=list)
    best: Hypothesis | None = None
    submaps: int = 0
    query_ms: list[float] = field(default_factory=list)   # one per submap matched
    rotations: list[float] = field(default_factory=list)  # the searched peaks [rad]


# -- layers ------------------------------------------------------------------------------------
@dataclass
class Layers:
    """One map at the search resolution: occupied, free, and a lookup of each at fine cells."""

    origin: F64
    cell_m: float
    occ: B          # coarse: any fine cell occupied
    free: B         # coarse: most fine cells free and none occupied
    fine_origin: F64
    fine_m: float
    fine_occ: B
    fine_free: B
    fine_near: B    # within one fine cell of an occupied one
    fine_clear: B   # free with no occupied cell within two
    code: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 0), np.uint8))

    occ_xy: F64 = field(default_factory=lambda: np.zeros((0, 2)))     # fine cell centres
    clear_xy: F64 = field(default_factory=lambda: np.zeros((0, 2)))   # (every other one)

    def __post_init__(self) -> None:
        self.code = (self.fine_near * 1 + self.fine_clear * 2 + self.fine_free * 4
                     + self.fine_occ * 8).astype(np.uint8)
        self.occ_xy = _fine_xy(self, self.fine_occ)
        self.clear_xy = _fine_xy(self, self.fine_clear)[::2]


def layers(grid: OccupancyGrid, cell_m: float) -> Layers:
    from scipy.ndimage import binary_dilation

    occ, free = grid.occupied_mask(), grid.free_mask()
    res = grid.resolution_m
    f = max(1, round(cell_m / res))
    h, w = occ.shape
    H, W = -(-h // f), -(-w // f)
    po = np.zeros((H * f, W * f), dtype=bool)
    pf = np.zeros((H * f, W * f), dtype=bool)
    po[:h, :w], pf[:h, :w] = occ, free
    occ_c = np.asarray(po.reshape(H, f, W, f).any(axis=(1, 3)))
    free_c = (pf.reshape(H, f, W, f).sum(axis=(1, 3)) * 2 > f * f) & ~occ_c
    near = binary_dilation(occ, iterations=1) if occ.size else occ
    clear = free & ~binary_dilation(occ, iterations=2) if occ.size else free
    return Layers(grid.origin.copy(), res * f, occ_c, free_c, grid.origin.copy(), res,
                  occ, free, near, clear)


def _cells(lay: Layers, xy: F64) -> tuple[NDArray[np.int64], NDArray[np.int64], B]:
    j = np.floor((xy[:, 0] - lay.fine_origin[0]) / lay.fine_m).astype(np.int64)
    i = np.floor((xy[:, 1] - lay.fine_origin[1]) / lay.fine_m).astype(np.int64)
    h, w = lay.fine_occ.shape
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    return i, j, ok


def _fine_xy(lay: Layers, mask: B) -> F64:
    i, j = np.nonzero(mask)
    return np.stack([lay.fine_origin[0] + (j + 0.5) * lay.fine_m,
                     lay.fine_origin[1] + (i + 0.5) * lay.fine_m], axis=1)


#: how far two hypotheses of a pair may differ and still be the same one
SAME_M, SAME_DEG = 1.0, 3.0


def same_transform(T1: F64, T2: F64, at_b: F64) -> bool:
    """Two transforms (b -> a) place the point ``at_b`` (b's frame; a pose's heading is left
    aside) within SAME_M and turn within SAME_DEG of each other."""
    if abs(wrap_angle(T1[2] - T2[2])) > math.radians(SAME_DEG):
        return False
    at = np.asarray(at_b, dtype=np.float64)[None, :2]    # a pose's position, or a point
    p1 = transform_points(T1, at)[0]
    p2 = transform_points(T2, at)[0]
    return math.hypot(*(p1 - p2)) <= SAME_M


# -- 3. consistency ----------------------------------------------------------------------------
def consistent(c1: Candidate, c2: Candidate, p: MatchParams) -> bool:
    """Two candidates imply the same transform: each one's submap lands within
    ``consistent_m`` under the other's transform (checked at both places, so a small turn far
    from the submaps counts), and their rotations agree."""
    if abs(wrap_angle(c1.T_ab[2] - c2.T_ab[2])) > math.radians(p.consistent_deg):
        return False
    for c in (c1, c2):
        xb = transform_points(inverse(c.T_ab), c.centre_a[None, :])   # the place in b's frame
        d1 = transform_points(c1.T_ab, xb)[0]
        d2 = transform_points(c2.T_ab, xb)[0]
        if math.hypot(*(d1 - d2)) > p.consistent_m:
            return False
    return True


def _max_clique(adj: list[set[int]], allowed: set[int]) -> list[int]:
    best: list[int] = []

    def grow(r: list[int], cand: set[int], excl: set[int]) -> None:
        nonlocal best
        if not cand and not excl:
            if len(r) > len(best):
                best = list(r)
            return
        if len(r) + len(cand) <= len(best):
            return
        pivot = max(cand | excl, key=lambda u: len(adj[u] & cand))
        for v in list(cand - adj[pivot]):
            grow([*r, v], cand & adj[v], excl & adj[v])
            cand = cand - {v}
            excl = excl | {v}

    grow([], set(allowed), set())
    return best


def places(members: list[Candidate], p: MatchParams) -> int:
    """How many distinct places (in a's frame, ``spacing_m`` / 2 apart) the members cover."""
    seen: list[F64] = []
    for c in members:
        if all(math.hypot(*(c.centre_a - q)) >= p.spacing_m / 2 for q in seen):
            seen.append(c.centre_a)
    return len(seen)


def best_hypothesis(cands: list[Candidate], p: MatchParams) -> Hypothesis | None:
    """The largest set of mutually consistent candidates (at most one per submap), and the
    support of the best set that contradicts it."""
    if not cands:
        return None
    n = len(cands)
    adj: list[set[int]] = [set() for _ in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            same = (cands[i].side, cands[i].submap) == (cands[j].side, cands[j].submap)
            if not same and consistent(cands[i], cands[j], p):
                adj[i].add(j)
                adj[j].add(i)
    clique = _max_clique(adj, set(range(n)))
    members = [cands[i] for i in clique]
    # the rival: the best set among candidates that contradict every member
    rivals = {i for i in range(n) if i not in clique and not any(i in adj[k] for k in clique)}
    rival = [cands[i] for i in _max_clique(adj, rivals)] if rivals else []
    T = _mean_transform([c.T_ab for c in members])
    clear = [c for c in members if _distinct(c, cands, p)]
    return Hypothesis(T, places(members, p), tuple(members), places(rival, p) if rival else 0,
                      float(np.mean([c.acceptance for c in members])), places(clear, p))


def _distinct(c: Candidate, cands: list[Candidate], p: MatchParams) -> bool:
    """``c`` is its submap's best placement, and the submap's next best scores at most
    ``p.distinct_ratio`` of it. In a building of repeated rooms a submap fits several places
    about equally well; a place only counts toward a merge where it fits one clearly best."""
    own = sorted((o for o in cands if (o.side, o.submap) == (c.side, c.submap)),
                 key=lambda o: -o.score)
    if own[0] is not c or c.score <= 0:
        return False
    return len(own) < 2 or own[1].score <= p.distinct_ratio * c.score


def _mean_transform(Ts: list[F64]) -> F64:
    th = math.atan2(sum(math.sin(T[2]) for T in Ts), sum(math.cos(T[2]) for T in Ts))
    xy = np.mean([T[:2] for T in Ts], axis=0)
    return np.array([xy[0], xy[1], th])


def transform_error(T: F64, T_true: F64) -> tuple[float, float]:
    """Position [m] and rotation [rad] of ``T`` against ``T_true``."""
    d = compose(inverse(T_true), T)
    return math.hypot(d[0], d[1]), abs(wrap_angle(d[2]))
