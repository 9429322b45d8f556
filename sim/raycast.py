"""Vectorised 2D ray casting against oriented segments and circles.

For one sensor pose the cost grows with the beams each obstacle covers, not beams × obstacles:
every segment within range that faces the sensor is turned into the interval of beam indices it
subtends, the (beam, segment) pairs are expanded with ``np.repeat``, and each pair's range is

    r = (a × e) / (d × e)

for a beam of direction ``d`` hitting the segment ``a + s e`` (``a`` relative to the sensor,
``×`` the 2D cross product). Circles ``(c, ρ)`` give ``r = |c| cos δ − sqrt(ρ² − |c|² sin² δ)``
for a beam at angle ``δ`` from the centre direction. Each beam keeps its nearest hit.
Beams must be evenly spaced: beam ``i`` points at ``angle_min + i * increment`` in the sensor
frame.
"""

from __future__ import annotations

import math

import numpy as np


class RayCaster:
    """Casts evenly spaced beams against a static set of segments plus per-call circles."""

    def __init__(self, segments: np.ndarray, circles: np.ndarray | None = None) -> None:
        seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
        length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        self.segments = np.ascontiguousarray(seg[length > 1e-12])
        self.circles = (np.zeros((0, 3)) if circles is None
                        else np.asarray(circles, dtype=np.float64).reshape(-1, 3))
        self._cache: dict[tuple[int, float, float], tuple[np.ndarray, np.ndarray, int]] = {}

    def _beams(self, n: int, angle_min: float, inc: float) -> tuple[np.ndarray, np.ndarray, int]:
        key = (n, angle_min, inc)
        got = self._cache.get(key)
        if got is None:
            a = angle_min + inc * np.arange(n)
            full = max(n, math.ceil(2 * math.pi / abs(inc) - 1e-9))
            got = (np.cos(a), np.sin(a), full)
            self._cache[key] = got
        return got

    def cast(self, pose: tuple[float, float, float], n: int, angle_min: float, inc: float,
             max_range: float, extra_circles: np.ndarray | None = None) -> np.ndarray:
        """Ranges [m] of ``n`` beams from ``pose`` (x, y, theta); ``inf`` where nothing is hit
        within ``max_range``."""
        if inc <= 0:
            raise ValueError("beam increment must be > 0")
        cos_b, sin_b, full = self._beams(n, angle_min, inc)
        out = np.full(n, np.inf)
        x0, y0, th = pose
        c, s = math.cos(th), math.sin(th)
        seg = self.segments
        if len(seg):
            # segment ends in the sensor frame
            dx1, dy1 = seg[:, 0] - x0, seg[:, 1] - y0
            dx2, dy2 = seg[:, 2] - x0, seg[:, 3] - y0
            ax, ay = c * dx1 + s * dy1, -s * dx1 + c * dy1
            bx, by = c * dx2 + s * dy2, -s * dx2 + c * dy2
            ex, ey = bx - ax, by - ay
            # facing: sensor on the right of a->b (obstacle on the left);
            # in range: distance from sensor to segment < max_range
            facing = ax * ey - ay * ex < 0.0
            t = np.clip(-(ax * ex + ay * ey) / (ex * ex + ey * ey), 0.0, 1.0)
            near = (ax + t * ex) ** 2 + (ay + t * ey) ** 2 < max_range * max_range
            keep = np.flatnonzero(facing & near)
            if len(keep):
                ax, ay, bx, by = ax[keep], ay[keep], bx[keep], by[keep]
                ex, ey = ex[keep], ey[keep]
                # seen from the sensor, b comes first counter-clockwise and a last
                start = np.arctan2(by, bx)
                span = np.mod(np.arctan2(ay, ax) - start, 2 * math.pi)
                self._fill(out, start, span, angle_min, inc, full, n, cos_b, sin_b,
                           lambda idx, cb, sb: _segment_range(ax[idx], ay[idx], ex[idx],
                                                              ey[idx], cb, sb))
        circ = self.circles if extra_circles is None or not len(extra_circles) else (
            np.vstack([self.circles, extra_circles]))
        if len(circ):
            dx, dy = circ[:, 0] - x0, circ[:, 1] - y0
            cx, cy = c * dx + s * dy, -s * dx + c * dy
            d = np.hypot(cx, cy)
            rho = circ[:, 2]
            ok = np.flatnonzero((d > rho) & (d - rho < max_range))
            if len(ok):
                cx, cy, d, rho = cx[ok], cy[ok], d[ok], rho[ok]
                half = np.arcsin(rho / d)
                centre = np.arctan2(cy, cx)
                self._fill(out, centre - half, 2 * half, angle_min, inc, full, n, cos_b, sin_b,
                           lambda idx, cb, sb: _circle_range(cx[idx], cy[idx], rho[idx], cb, sb))
        out[out > max_range] = np.inf
        return out

    @staticmethod
    def _fill(out: np.ndarray, start: np.ndarray, span: np.ndarray, angle_min: float,
              inc: float, full: int, n: int, cos_b: np.ndarray, sin_b: np.ndarray,
              ranges: object) -> None:
        """Expand each obstacle's angular interval [start, start+span] into beam indices and
        keep the minimum range per beam."""
        rel = np.mod(start - angle_min, 2 * math.pi) / inc
        lo = np.ceil(rel - 1e-9).astype(np.int64)
        hi = np.floor(rel + span / inc + 1e-9).astype(np.int64)
        counts = np.maximum(hi - lo + 1, 0)
        total = int(counts.sum())
        if total == 0:
            return
        owner = np.repeat(np.arange(len(lo)), counts)
        offset = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
        beam = (lo[owner] + offset) % full
        inside = beam < n
        owner, beam = owner[inside], beam[inside]
        r = ranges(owner, cos_b[beam], sin_b[beam])  # type: ignore[operator]
        valid = r > 0
        np.minimum.at(out, beam[valid], r[valid])


def _segment_range(ax: np.ndarray, ay: np.ndarray, ex: np.ndarray, ey: np.ndarray,
                   dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Distance along unit beams (dx, dy) to the lines a + s e: (a × e) / (d × e)."""
    denom = dx * ey - dy * ex
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (ax * ey - ay * ex) / denom
    return np.where(np.isfinite(r), r, np.inf)


def _circle_range(cx: np.ndarray, cy: np.ndarray, rho: np.ndarray, dx: np.ndarray,
                  dy: np.ndarray) -> np.ndarray:
    """Distance along unit beams (dx, dy) to the near side of circles (c, rho)."""
    proj = cx * dx + cy * dy                      # |c| cos δ
    perp2 = (cx * dy - cy * dx) ** 2              # |c|² sin² δ
    disc = rho * rho - perp2
    return np.where(disc >= 0, proj - np.sqrt(np.maximum(disc, 0.0)), np.inf)


def line_of_sight(p: tuple[float, float], q: tuple[float, float], segments: np.ndarray,
                  circles: np.ndarray | None = None) -> bool:
    """True when the straight line p -> q crosses no segment and no circle ``(x, y, r)``."""
    px, py = p
    dx, dy = q[0] - px, q[1] - py
    if len(segments):
        ax, ay = segments[:, 0] - px, segments[:, 1] - py
        ex, ey = segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1]
        denom = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * ey - ay * ex) / denom      # along p -> q
            u = (ax * dy - ay * dx) / denom      # along the segment
        if np.any((denom != 0) & (t > 0) & (t < 1) & (u >= 0) & (u <= 1)):
            return False
    if circles is not None and len(circles):
        L2 = dx * dx + dy * dy
        if L2 > 0:
            cx, cy = circles[:, 0] - px, circles[:, 1] - py
            t = np.clip((cx * dx + cy * dy) / L2, 0.0, 1.0)
            d2 = (cx - t * dx) ** 2 + (cy - t * dy) ** 2
            if np.any(d2 < circles[:, 2] ** 2):
                return False
    return True
