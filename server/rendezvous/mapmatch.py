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

No I/O and no server state here: ``match_pair`` takes two grids and keyframe positions.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft
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


# -- 1. rotations ------------------------------------------------------------------------------
def hough_spectrum(occ: B) -> F64:
    """Per line direction (1° bins over 180°), the sum of squared Hough votes above their
    median, normalised."""
    from skimage.transform import hough_line

    if occ.sum() < 10:
        return np.zeros(180)
    theta = np.deg2rad(np.arange(180) - 90.0)
    acc, _, _ = hough_line(occ, theta=theta)
    s = (acc.astype(np.float64) ** 2).sum(axis=0)
    # scattered cells give every direction some votes: only what stands out is a wall
    s = np.clip(s - np.median(s), 0.0, None)
    n = float(np.linalg.norm(s))
    return s / n if n > 0 else s


def rotation_peaks(spec_a: F64, spec_b: F64, max_peaks: int = 4) -> list[float]:
    """Rotations [rad] (b -> a) that bring b's wall directions onto a's, both half-turns of
    each peak of the spectra's circular cross-correlation. Line directions rotate like the
    map, so b's spectrum shifted by the rotation matches a's."""
    if not spec_a.any() or not spec_b.any():
        return []
    cc = np.real(np.fft.ifft(np.fft.fft(spec_a) * np.conj(np.fft.fft(spec_b))))
    order = np.argsort(cc)[::-1]
    peaks: list[int] = []
    for k in order:
        if cc[k] < 0.5 * cc[order[0]] or len(peaks) >= max_peaks:
            break
        if all(min(abs(k - q), 180 - abs(k - q)) > 8 for q in peaks):
            peaks.append(int(k))
    out = []
    for k in peaks:
        out += [math.radians(k), math.radians(k + 180)]
    return [wrap_angle(a) for a in out]


# -- 2. candidates -----------------------------------------------------------------------------
def submap_centres(positions: F64, lay: Layers, p: MatchParams) -> list[F64]:
    """Keyframe positions at least ``spacing_m`` apart whose square holds enough walls, the
    most walled first (at most ``max_submaps``)."""
    if not len(positions):
        return []
    picked: list[F64] = []
    for xy in positions[::-1]:           # newest first: it is where the map grows
        if all(math.hypot(*(xy - q)) >= p.spacing_m for q in picked):
            picked.append(np.asarray(xy, dtype=np.float64))
    walls = [int(_window(lay, c, p.submap_m)[0].sum()) for c in picked]
    keep = [c for c, n in sorted(zip(picked, walls, strict=True), key=lambda x: -x[1])
            if n >= p.min_submap_walls]
    return keep[:p.max_submaps]


def _window(lay: Layers, centre: F64, side_m: float) -> tuple[B, B, F64]:
    """The coarse occupied and free cells of a square around ``centre``, and its corner."""
    half = side_m / 2
    j0 = max(0, math.floor((centre[0] - half - lay.origin[0]) / lay.cell_m))
    i0 = max(0, math.floor((centre[1] - half - lay.origin[1]) / lay.cell_m))
    n = math.ceil(side_m / lay.cell_m)
    occ = lay.occ[i0:i0 + n, j0:j0 + n]
    free = lay.free[i0:i0 + n, j0:j0 + n]
    corner = lay.origin + np.array([j0, i0]) * lay.cell_m
    return occ, free, corner


def _points(mask: B, corner: F64, cell_m: float) -> F64:
    i, j = np.nonzero(mask)
    return np.stack([corner[0] + (j + 0.5) * cell_m, corner[1] + (i + 0.5) * cell_m], axis=1)


def _raster(pts: F64, lo: F64, out: NDArray[np.float32], cell_m: float) -> None:
    """Mark the cells of ``out`` (corner ``lo``) that hold a point."""
    j = np.floor((pts[:, 0] - lo[0]) / cell_m).astype(np.int64)
    i = np.floor((pts[:, 1] - lo[1]) / cell_m).astype(np.int64)
    ok = (i >= 0) & (i < out.shape[0]) & (j >= 0) & (j < out.shape[1])
    out[i[ok], j[ok]] = 1.0


class Target:
    """The map a submap is matched against, with the FFTs of its layers kept for all rotations
    and submaps of a query."""

    def __init__(self, lay: Layers, submap_m: float, weight: float) -> None:
        from scipy.ndimage import binary_dilation

        self.lay = lay
        self.m = math.ceil(submap_m * 1.5 / lay.cell_m) + 2   # a rotated submap fits
        from scipy.fft import next_fast_len

        H, W = lay.occ.shape
        self.shape = (next_fast_len(H + self.m, real=True), next_fast_len(W + self.m, real=True))
        near = binary_dilation(lay.occ, iterations=1) if lay.occ.size else lay.occ
        clear = lay.free & ~near
        for_walls = (near.astype(np.float32) - np.float32(weight) * clear).astype(np.float32)
        self.F_walls = sfft.rfft2(for_walls, self.shape)
        self.F_occ = np.float32(weight) * sfft.rfft2(lay.occ.astype(np.float32), self.shape)
        self.weight = weight

    def scores(self, occ_r: NDArray[np.float32], free_r: NDArray[np.float32]
               ) -> NDArray[np.float32]:
        """For every shift (di, dj) of each rasterised submap's corner (a stack, one per
        rotation) onto the map's cell (di, dj), negative shifts wrapped around: hits −
        weight · conflicts, by correlation through the FFT (single precision: the scores
        are counts of a few thousand at most)."""
        Fo = sfft.rfft2(occ_r, self.shape, axes=(-2, -1))
        Ff = sfft.rfft2(free_r, self.shape, axes=(-2, -1))
        prod = self.F_walls * np.conj(Fo) - self.F_occ * np.conj(Ff)
        return np.asarray(sfft.irfft2(prod, self.shape, axes=(-2, -1)))


def match_submap(src: Layers, centre: F64, dst: Target, rotations: list[float],
                 p: MatchParams, side: str, index: int, to_ab: bool) -> list[Candidate]:
    """The best ``top_k`` placements of src's submap around ``centre`` in dst's map.
    ``to_ab``: src is b (the placements are T_ab); else src is a (they are inverted)."""
    occ, free, corner = _window(src, centre, p.submap_m)
    pts_o, pts_f = _points(occ, corner, src.cell_m), _points(free, corner, src.cell_m)
    if len(pts_o) < p.min_submap_walls:
        return []
    lay, m, cell = dst.lay, dst.m, dst.lay.cell_m
    found: list[tuple[float, float, F64]] = []     # (score, angle, translation)
    steps = np.arange(-p.window_deg, p.window_deg + 1e-9, p.step_deg)
    angles = [wrap_angle(base + math.radians(d)) for base in rotations for d in steps]
    So = np.zeros((len(angles), m, m), dtype=np.float32)
    Sf = np.zeros((len(angles), m, m), dtype=np.float32)
    turns, corners = [], []
    for k, th in enumerate(angles):
        c, s = math.cos(th), math.sin(th)
        R = np.array([[c, -s], [s, c]])
        ro, rf = (pts_o - centre) @ R.T, (pts_f - centre) @ R.T
        lo = np.minimum(ro.min(axis=0), rf.min(axis=0) if len(rf) else ro.min(axis=0))
        _raster(ro, lo, So[k], cell)
        _raster(rf, lo, Sf[k], cell)
        turns.append(R)
        corners.append(lo)
    sc = dst.scores(So, Sf)
    H, W = sc.shape[1:]
    for k, th in enumerate(angles):
        flat_k = sc[k].ravel()
        for f in np.argpartition(flat_k, -8)[-8:]:   # the strongest shifts of this rotation
            i, j = divmod(int(f), W)
            di = i if i < H - m else i - H
            dj = j if j < W - m else j - W
            # the raster's corner lands on map cell (di, dj): centre -> where
            where = lay.origin + np.array([dj, di]) * cell - corners[k]
            found.append((float(flat_k[f]), th, where - turns[k] @ centre))
    found.sort(key=lambda x: -x[0])
    out: list[Candidate] = []
    placed: list[tuple[F64, float]] = []     # kept placements: centre in dst, angle
    tried = 0
    for score, th, t in found:
        T = np.array([t[0], t[1], th])
        at = transform_points(T, centre[None, :])[0]
        if any(math.hypot(*(at - q)) < p.peak_separation_m
               and abs(wrap_angle(th - a)) < math.radians(10.0) for q, a in placed):
            continue
        placed.append((at, th))
        tried += 1
        cand = _refine(src, centre, dst.lay, T, p, side, index, to_ab, score)
        if cand is not None:
            out.append(cand)
        if len(out) >= p.top_k or tried >= p.top_k + 2:
            break
    return out


def _refine(src: Layers, centre: F64, dst: Layers, T: F64, p: MatchParams, side: str,
            index: int, to_ab: bool, score: float) -> Candidate | None:
    """A small search on the fine grid around a coarse placement (±0.5°, ±1 cell), scored by
    the acceptance index; None when the overlap is too small or disagrees."""
    half = p.submap_m / 2
    po, pf = src.occ_xy, src.clear_xy
    po = po[(np.abs(po - centre) <= half).all(axis=1)]
    pf = pf[(np.abs(pf - centre) <= half).all(axis=1)]
    code = dst.code
    h, w = code.shape
    best: tuple[float, F64, int, int, float, int] | None = None
    step = dst.fine_m
    for dth in np.radians((-0.5, 0.0, 0.5)):
        th = T[2] + dth
        c, s = math.cos(th), math.sin(th)
        R = np.array([[c, -s], [s, c]])
        # turned about the submap centre, so that turning does not shift it
        t0 = transform_points(T, centre[None, :])[0] - R @ centre
        io, jo, _ = _cells(dst, po @ R.T + t0)
        i_f, j_f, _ = _cells(dst, pf @ R.T + t0)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                no = _codes(code, io + dy, jo + dx, h, w)
                nf = _codes(code, i_f + dy, j_f + dx, h, w)
                hits, wall_bad = int(no[NEAR].sum()), int(no[CLEAR].sum())
                free_ok, free_bad = int(nf[FREE].sum()), int(nf[OCC].sum())
                val = hits - p.conflict_weight * (wall_bad + free_bad)
                if best is None or val > best[0]:
                    agree, dis = hits + free_ok, wall_bad + free_bad
                    known = int(no[OCC | FREE].sum()) + free_ok + free_bad
                    best = (val, np.array([t0[0] + dx * step, t0[1] + dy * step, th]), hits,
                            dis, agree / max(1, agree + dis), known)
    assert best is not None
    _, Tf, hits, bad, acc, overlap = best
    per_cell = src.cell_m / src.fine_m   # fine wall cells along a wall per coarse one
    if hits < p.min_hits * per_cell or acc < p.min_acceptance:
        return None
    T_ab = Tf if to_ab else inverse(Tf)
    centre_a = transform_points(Tf, centre[None, :])[0] if to_ab else centre.copy()
    return Candidate(T_ab, side, index, centre_a, score, hits, bad, round(acc, 4), overlap)


#: bits of ``Layers.code``, and masks over its 16 values selecting those with the bit set
_BITS = np.arange(16)
NEAR, CLEAR, FREE, OCC = ((_BITS & b) > 0 for b in (1, 2, 4, 8))


def _codes(code: NDArray[np.uint8], i: NDArray[np.int64], j: NDArray[np.int64], h: int,
           w: int) -> NDArray[np.int64]:
    """How many of the cells (i, j) inside the grid have each code."""
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    return np.bincount(code[i[ok], j[ok]], minlength=16)


def _fine_xy(lay: Layers, mask: B) -> F64:
    i, j = np.nonzero(mask)
    return np.stack([lay.fine_origin[0] + (j + 0.5) * lay.fine_m,
                     lay.fine_origin[1] + (i + 0.5) * lay.fine_m], axis=1)


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


# -- a query of one pair -----------------------------------------------------------------------
def submap_candidates(grid_a: OccupancyGrid, grid_b: OccupancyGrid,
                      centres_a: list[tuple[int, F64]], centres_b: list[tuple[int, F64]],
                      p: MatchParams | None = None) -> PairResult:
    """The candidates of the given submaps (ids and centres, each in its own team's frame):
    b's placed on a's map, a's on b's. No hypothesis (``best`` stays None)."""
    p = p or MatchParams()
    la, lb = layers(grid_a, p.cell_m), layers(grid_b, p.cell_m)
    res = PairResult()
    rot = rotation_peaks(hough_spectrum(la.occ), hough_spectrum(lb.occ), p.max_rotation_peaks)
    res.rotations = rot
    if not rot:
        return res
    ta, tb = Target(la, p.submap_m, p.conflict_weight), Target(lb, p.submap_m,
                                                                 p.conflict_weight)
    back = [wrap_angle(-r) for r in rot]
    for side, src, centres, dst, rots in (("b", lb, centres_b, ta, rot),
                                          ("a", la, centres_a, tb, back)):
        for k, c in centres:
            if int(_window(src, c, p.submap_m)[0].sum()) < p.min_submap_walls:
                continue
            t0 = time.perf_counter()
            res.candidates += match_submap(src, c, dst, rots, p, side, k, to_ab=side == "b")
            res.query_ms.append((time.perf_counter() - t0) * 1e3)
            res.submaps += 1
    return res


def match_pair(grid_a: OccupancyGrid, grid_b: OccupancyGrid, kf_a: F64, kf_b: F64,
               p: MatchParams | None = None) -> PairResult:
    """Submaps of each team's map (around its keyframes ``kf_*``, positions in its own team
    frame) matched against the other's map, and the best hypothesis over all of them."""
    p = p or MatchParams()
    la, lb = layers(grid_a, p.cell_m), layers(grid_b, p.cell_m)
    res = submap_candidates(grid_a, grid_b, list(enumerate(submap_centres(kf_a, la, p))),
                            list(enumerate(submap_centres(kf_b, lb, p))), p)
    res.best = best_hypothesis(res.candidates, p)
    return res


def transform_error(T: F64, T_true: F64) -> tuple[float, float]:
    """Position [m] and rotation [rad] of ``T`` against ``T_true``."""
    d = compose(inverse(T_true), T)
    return math.hypot(d[0], d[1]), abs(wrap_angle(d[2]))
