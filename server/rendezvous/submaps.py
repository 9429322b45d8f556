"""Steps 1 and 2 of matching two teams' maps (``server.rendezvous.mapmatch``): the rotations
their walls allow, each submap's candidates placed by FFT correlation and refined, and a query
of one pair of maps. No I/O and no server state."""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.fft as sfft
from numpy.typing import NDArray

from schemas.se2 import inverse, transform_points, wrap_angle
from server.rendezvous.mapmatch import (
    F64,
    B,
    Candidate,
    Layers,
    MatchParams,
    PairResult,
    _cells,
    best_hypothesis,
    layers,
)
from server.slam.grid import OccupancyGrid


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


