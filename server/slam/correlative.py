"""Correlative scan matching over a search window by branch and bound (Olson 2009; Hess et al.
2016), vectorised over candidates.

The map becomes a likelihood field L(c) = exp(−d(c)² / 2σ²), d = distance from cell c to the
nearest cell holding a map point (cut off at 3σ). The score of a pose T for scan points p_i is
the mean of L at the cells of T·p_i. A precomputed max-pyramid L_h(y, x) = max of L over the
2^h × 2^h cells starting at (y, x) bounds the score of every translation in a 2^h-cell block
from above, so whole blocks are discarded when their bound is below the best exact score.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import wrap_angle

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
MAX_SURVIVORS = 30000
#: cells looked up per chunk of candidates: each chunk's index arrays take 16 bytes a cell
#: (4 MB here; two million cells took about 50 MB of short-lived arrays at once)
CHUNK_CELLS = 250_000


@dataclass(frozen=True)
class CorrelativeMatch:
    """Best pose, its score (mean likelihood, 0..1) and the best score of a distinct pose."""

    T_map_scan: F64
    score: float
    second_score: float = 0.0


def gaussian_max_filter(hits: NDArray[np.float32], sigma_cells: float) -> NDArray[np.float32]:
    """L(c) = max over hit cells h of exp(−|c − h|² / 2σ²), cut off at 3σ.

    The kernel is separable and non-negative, so the max splits into a pass along y and one
    along x: max_{dx,dy} g(dx) g(dy) h(x+dx, y+dy) = max_dx g(dx) max_dy g(dy) h(x+dx, y+dy).
    """
    radius = max(1, math.ceil(3.0 * sigma_cells))
    g = np.exp(-0.5 * (np.arange(radius + 1) / sigma_cells) ** 2).astype(np.float32)
    tmp = hits.copy()
    for d in range(1, radius + 1):
        np.maximum(tmp[:-d], g[d] * hits[d:], out=tmp[:-d])
        np.maximum(tmp[d:], g[d] * hits[:-d], out=tmp[d:])
    out = tmp.copy()
    for d in range(1, radius + 1):
        np.maximum(out[:, :-d], g[d] * tmp[:, d:], out=out[:, :-d])
        np.maximum(out[:, d:], g[d] * tmp[:, :-d], out=out[:, d:])
    return out


class LikelihoodField:
    """Likelihood field of map points and its max-pyramid. Row index = y, column index = x."""

    def __init__(self, points_map: F64, resolution_m: float, sigma_m: float, margin_m: float,
                 levels: int) -> None:
        self.resolution_m = resolution_m
        lo = points_map.min(axis=0) - margin_m
        hi = points_map.max(axis=0) + margin_m
        self.origin = lo
        shape = np.ceil((hi - lo) / resolution_m).astype(np.int64) + 1
        w, h = int(shape[0]), int(shape[1])
        hits = np.zeros((h, w), dtype=np.float32)
        ij = np.floor((points_map - lo) / resolution_m).astype(np.int64)
        hits[ij[:, 1], ij[:, 0]] = 1.0
        field = gaussian_max_filter(hits, sigma_m / resolution_m)
        field[0, :] = field[-1, :] = 0.0  # a zero border: indices are clipped onto it
        field[:, 0] = field[:, -1] = 0.0
        self.pyramid = [field]
        for lv in range(1, levels + 1):
            s = 1 << (lv - 1)
            prev = self.pyramid[-1]
            nxt = prev.copy()
            nxt[:, :-s] = np.maximum(nxt[:, :-s], prev[:, s:])
            nxt[:-s, :] = np.maximum(nxt[:-s, :], nxt[s:, :])
            self.pyramid.append(nxt)

    @property
    def levels(self) -> int:
        return len(self.pyramid) - 1

    def cells(self, xy: F64) -> I64:
        return np.floor((xy - self.origin) / self.resolution_m).astype(np.int64)

    def score(self, points_map: F64) -> float:
        """Mean likelihood of points already in the map frame."""
        f = self.pyramid[0]
        ij = self.cells(points_map)
        ix = np.clip(ij[:, 0], 0, f.shape[1] - 1)
        iy = np.clip(ij[:, 1], 0, f.shape[0] - 1)
        return float(f[iy, ix].mean())


def angle_step(points: F64, resolution_m: float, lo_rad: float = math.radians(0.25),
               hi_rad: float = math.radians(2.0)) -> float:
    """Angular step [rad] moving the far points by about one cell: acos(1 − r²/(2 d²))."""
    d = float(np.percentile(np.hypot(points[:, 0], points[:, 1]), 90)) if len(points) else 1.0
    step = math.acos(max(-1.0, 1.0 - resolution_m ** 2 / (2.0 * max(d, 1e-3) ** 2)))
    return min(max(step, lo_rad), hi_rad)


def _evaluate(level: NDArray[np.float32], cx: I64, cy: I64, a: I64, dx: I64, dy: I64) -> F64:
    """Mean of ``level`` over the points of candidates (angle index a, offset dx, dy)."""
    h, w = level.shape
    out = np.empty(len(a), dtype=np.float64)
    chunk = max(1, CHUNK_CELLS // max(cx.shape[1], 1))
    for s in range(0, len(a), chunk):
        sl = slice(s, s + chunk)
        ix = cx[a[sl]]
        ix += dx[sl, None]
        np.clip(ix, 0, w - 1, out=ix)
        iy = cy[a[sl]]
        iy += dy[sl, None]
        np.clip(iy, 0, h - 1, out=iy)
        out[sl] = level[iy, ix].mean(axis=1)
    return out


def _children(a: I64, dx: I64, dy: I64, h: int, W: int) -> tuple[I64, I64, I64]:
    """The four 2^lv-blocks inside each 2^(lv+1)-block, kept within the ±W window."""
    a4 = np.repeat(a, 4)
    dx4 = np.repeat(dx, 4) + np.tile(np.array([0, h, 0, h]), len(dx))
    dy4 = np.repeat(dy, 4) + np.tile(np.array([0, 0, h, h]), len(dy))
    inside = (np.abs(dx4) <= W) & (np.abs(dy4) <= W)
    return a4[inside], dx4[inside], dy4[inside]


def search(field: LikelihoodField, points: F64, T_center: F64, window_m: float,
           window_rad: float, min_score: float, ambiguity_ratio: float | None = None,
           separation_m: float = 0.3, separation_rad: float = math.radians(5.0)
           ) -> CorrelativeMatch | None:
    """Best pose within ±``window_m`` (x, y) and ±``window_rad`` of ``T_center``, or None if no
    pose scores ``min_score``. ``points`` are in the scan frame.

    With ``ambiguity_ratio`` ρ, blocks are kept while they could score ρ·best, and
    ``second_score`` reports the best pose at least ``separation_m`` or ``separation_rad``
    away from the best one (0 if none reaches ρ·best): a second peak almost as good means the
    place is ambiguous (a corridor, repeated rooms).
    """
    res = field.resolution_m
    step = angle_step(points, res)
    n_ang = math.ceil(window_rad / step)
    thetas = T_center[2] + step * np.arange(-n_ang, n_ang + 1)
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    gx = c * points[:, 0] - s * points[:, 1] + T_center[0]
    gy = s * points[:, 0] + c * points[:, 1] + T_center[1]
    cx = np.floor((gx - field.origin[0]) / res).astype(np.int64)
    cy = np.floor((gy - field.origin[1]) / res).astype(np.int64)
    W = math.ceil(window_m / res)
    top = min(field.levels, max(0, math.floor(math.log2(max(2 * W + 1, 1)))))
    offs = np.arange(-W, W + 1, 1 << top, dtype=np.int64)
    A, X, Y = np.meshgrid(np.arange(len(thetas)), offs, offs, indexing="ij")
    a, dx, dy = A.ravel(), X.ravel(), Y.ravel()
    bound = _evaluate(field.pyramid[top], cx, cy, a, dx, dy)
    # a greedy dive from the best block gives a first exact score to prune with
    k = int(np.argmax(bound))
    ga, gdx, gdy = a[k:k + 1], dx[k:k + 1], dy[k:k + 1]
    for lv in range(top - 1, -1, -1):
        ca, cdx, cdy = _children(ga, gdx, gdy, 1 << lv, W)
        sc = _evaluate(field.pyramid[lv], cx, cy, ca, cdx, cdy)
        j = int(np.argmax(sc))
        ga, gdx, gdy = ca[j:j + 1], cdx[j:j + 1], cdy[j:j + 1]
    dive = float(_evaluate(field.pyramid[0], cx, cy, ga, gdx, gdy)[0])
    ratio = 1.0 if ambiguity_ratio is None else ambiguity_ratio
    threshold = max(min_score, ratio * dive)
    for lv in range(top - 1, -1, -1):
        keep = bound >= threshold
        a, dx, dy, bound = a[keep], dx[keep], dy[keep], bound[keep]
        if len(a) > MAX_SURVIVORS:
            order = np.argsort(-bound)[:MAX_SURVIVORS]
            a, dx, dy, bound = a[order], dx[order], dy[order], bound[order]
        a, dx, dy = _children(a, dx, dy, 1 << lv, W)
        bound = _evaluate(field.pyramid[lv], cx, cy, a, dx, dy)
    # now ``bound`` holds exact scores of the surviving poses (plus the dive's)
    a = np.append(a, ga)
    dx, dy = np.append(dx, gdx), np.append(dy, gdy)
    scores = np.append(bound, dive)
    j = int(np.argmax(scores))
    best_score = float(scores[j])
    if best_score < min_score:
        return None
    far = (np.hypot(dx - dx[j], dy - dy[j]) * res > separation_m) | \
        (np.abs(a - a[j]) * step > separation_rad)
    second = float(scores[far].max()) if far.any() else 0.0
    T = np.array([T_center[0] + dx[j] * res, T_center[1] + dy[j] * res,
                  wrap_angle(float(thetas[a[j]]))])
    return CorrelativeMatch(T, best_score, second if second >= ratio * best_score else 0.0)
