"""The simulated world: obstacle cross-sections in the LIDAR's horizontal plane.

A world is what a 2D LIDAR at ``lidar_height_m`` can hit: convex polygons (walls and boxes cut by
the plane), circles (upright cylinders, spheres) and, derived from them, oriented segments for ray
casting. A segment ``(x1, y1, x2, y2)`` has the obstacle on its left (polygons are stored
counter-clockwise), so a ray can skip segments it meets from behind.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class World:
    name: str
    source: str
    polygons: tuple[np.ndarray, ...]
    circles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    lidar_height_m: float = 0.2

    @classmethod
    def from_shapes(cls, name: str, source: str, polygons: list[np.ndarray],
                    circles: list[tuple[float, float, float]] | np.ndarray,
                    lidar_height_m: float = 0.2,
                    segments: np.ndarray | None = None) -> World:
        """Build a world; polygons are made counter-clockwise and their edges become segments
        unless ``segments`` (already oriented) are given."""
        polys = tuple(ccw(np.asarray(p, dtype=np.float64)) for p in polygons)
        if segments is None:
            edges = [np.hstack([p, np.roll(p, -1, axis=0)]) for p in polys]
            segments = np.vstack(edges) if edges else np.zeros((0, 4))
        circ = np.asarray(circles, dtype=np.float64).reshape(-1, 3)
        return cls(name=name, source=source, polygons=polys, circles=circ,
                   segments=np.ascontiguousarray(segments, dtype=np.float64),
                   lidar_height_m=lidar_height_m)

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of every obstacle [m]; zeros for an empty world."""
        pts = [p for p in self.polygons]
        if len(self.circles):
            c = self.circles
            pts.append(np.column_stack([c[:, 0] - c[:, 2], c[:, 1] - c[:, 2]]))
            pts.append(np.column_stack([c[:, 0] + c[:, 2], c[:, 1] + c[:, 2]]))
        if len(self.segments):
            pts.append(self.segments[:, :2])
        if not pts:
            return (0.0, 0.0, 0.0, 0.0)
        allp = np.vstack(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))

    def summary(self) -> dict[str, object]:
        xmin, ymin, xmax, ymax = self.bounds()
        return {"name": self.name, "source": self.source, "polygons": len(self.polygons),
                "circles": len(self.circles), "segments": len(self.segments),
                "bounds_m": [xmin, ymin, xmax, ymax],
                "bbox_m2": (xmax - xmin) * (ymax - ymin)}


def ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon's vertices in counter-clockwise order (shoelace sign)."""
    x, y = poly[:, 0], poly[:, 1]
    area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    return poly[::-1].copy() if area2 < 0 else poly


def convex_hull(points: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """Counter-clockwise convex hull of (N, 2) points (Andrew's monotone chain)."""
    pts = sorted({(round(float(p[0]), 12), round(float(p[1]), 12)) for p in points})
    if len(pts) < 3:
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= eps:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= eps:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)
