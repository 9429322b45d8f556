"""Time of one exploration decision (skeleton, candidates, path) on a large partially explored
house; prints JSON.

The map is built the way a robot builds it: a 900 × 900 grid at 8 cells/m (the dissertation's
large-world setting) starts unknown; a robot with a 400-beam, 10 m LIDAR (σ = 8 mm) starts at the
scenario's spawn pose in ``house_large.world`` and, decision after decision, is moved along the
decided path (all of it, or its first ``--step-m``), scanning every 0.5 m (beams mark free cells,
hits occupied ones, poses exact), until the coverage threshold (90 % of 2500 m²) is reached. Every
decision is timed on the map as it is at that moment, so the samples span early (little known) to
late (most of the house known) exploration.

    python bench/decision.py [--decisions N] [--explorer voronoi|frontier] [--lam L]
                             [--world PATH] [--start X,Y,YAW] [--seed S]

Figures: ``decision_ms`` = one ``Explorer.decide`` call (coverage, crop, cost layer, Voronoi
skeleton + graph, rule-1 candidates and frontiers, Dijkstra from the robot, path lengths to the
candidates, the chosen path and its shortcutting); ``analysis_ms`` and ``dijkstra_ms`` time those
two stages again on their own; ``astar_ms`` is a single-query A* (``server.planning.plan``) from
the robot to the chosen target. ``replan``: half way along each path (the map has grown), the
target is replanned as the server does it — around the robot and the target first
(``server.exploration.replan``) — and on the whole map, with both times, whether both
answers agree (a path, or none) and the ratio of their path lengths.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from schemas.occupancy import FREE, OCCUPIED, UNKNOWN
from server.exploration import (
    Decision,
    ExplorerParams,
    Finished,
    VisitedTargets,
    analyse,
    coverage,
    make_explorer,
)
from server.planning import CostField, OccupancyGrid, PlanningError, plan

ROOT = Path(__file__).resolve().parent.parent
# Run as ``python bench/decision.py``, this folder comes first on sys.path and bench/sim.py would
# hide the ``sim`` package (imported inside main()).
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]
WORLD = ROOT.parent / "shared" / "data" / "worlds" / "thesis" / "house_large.world"
RES_M = 1.0 / 8.0
CELLS = 900
BEAMS, RANGE_M, NOISE_M = 400, 10.0, 0.008
TOTAL_AREA_M2 = 2500.0


class Mapper:
    """A grid filled by exact-pose scans: cells a beam crosses become free, hit cells occupied
    (and stay so)."""

    def __init__(self, caster: Any, rng: np.random.Generator) -> None:
        self.caster = caster
        self.rng = rng
        self.data = np.full((CELLS, CELLS), UNKNOWN, np.int8)
        self.origin = (-CELLS * RES_M / 2, -CELLS * RES_M / 2)
        self.occupied = np.zeros((CELLS, CELLS), bool)

    def grid(self) -> OccupancyGrid:
        return OccupancyGrid(self.data, RES_M, self.origin)

    def scan(self, pose: tuple[float, float, float]) -> None:
        ranges = self.caster.cast(pose, BEAMS, -math.pi, 2 * math.pi / BEAMS, RANGE_M)
        hit = np.isfinite(ranges)
        ranges = np.where(hit, ranges + self.rng.normal(0, NOISE_M, BEAMS), RANGE_M)
        ang = pose[2] - math.pi + 2 * math.pi / BEAMS * np.arange(BEAMS)
        d = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        t = np.arange(0.0, RANGE_M, RES_M / 2)
        along = t[None, :] < (ranges[:, None] - RES_M / 2)
        pts = np.asarray(pose[:2]) + (t[None, :, None] * d[:, None, :])[along]
        self._set(pts, FREE)
        self._set(np.asarray(pose[:2]) + ranges[hit, None] * d[hit], OCCUPIED)

    def _set(self, xy: np.ndarray, value: int) -> None:
        col = np.floor((xy[:, 0] - self.origin[0]) / RES_M).astype(np.int64)
        row = np.floor((xy[:, 1] - self.origin[1]) / RES_M).astype(np.int64)
        ok = (row >= 0) & (row < CELLS) & (col >= 0) & (col < CELLS)
        row, col = row[ok], col[ok]
        if value == OCCUPIED:
            self.occupied[row, col] = True
            self.data[row, col] = OCCUPIED
        else:
            keep = ~self.occupied[row, col]
            self.data[row[keep], col[keep]] = FREE


def walk(path_xy: np.ndarray, step_m: float, every_m: float
         ) -> list[tuple[float, float, float]]:
    """Poses every ``every_m`` along the first ``step_m`` of a path, heading along it."""
    seg = np.diff(path_xy, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    cum = np.concatenate([[0.0], np.cumsum(length)])
    out = []
    for s in np.append(np.arange(every_m, min(step_m, cum[-1]), every_m), min(step_m, cum[-1])):
        i = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
        if length[i] <= 0:
            continue
        f = (s - cum[i]) / length[i]
        p = path_xy[i] + f * seg[i]
        out.append((float(p[0]), float(p[1]), math.atan2(seg[i, 1], seg[i, 0])))
    return out


def compare_replans(grid: OccupancyGrid, pose: tuple[float, float, float],
                    target_xy: tuple[float, float], explorer: Any,
                    out: list[dict[str, Any]]) -> None:
    """A replan half way to the target, as the server does it (around the robot and its
    target first) and on the whole map: times, answers and path lengths."""
    from server.exploration.replan import Replan, _replan_on, replan, replan_window

    job = Replan(grid, explorer.params.analysis, explorer.walls_seen, (pose[0], pose[1]),
                 target_xy, 1.5)
    t0 = time.perf_counter()
    fast = replan(job)
    t1 = time.perf_counter()
    full = _replan_on(grid, job)
    t2 = time.perf_counter()

    def length(a: Any) -> float | None:
        if a.path_xy is None:
            return None
        return float(np.hypot(*np.diff(a.path_xy, axis=0).T).sum())

    out.append({"ms": (t1 - t0) * 1e3, "full_ms": (t2 - t1) * 1e3,
                "windowed": replan_window(job) is not None,
                "same_answer": (fast.path_xy is None) == (full.path_xy is None),
                "length": length(fast), "full_length": length(full)})


def replan_figures(rows: list[dict[str, Any]]) -> dict[str, Any]:
    if not rows:
        return {}
    ms = np.array([r["ms"] for r in rows])
    full = np.array([r["full_ms"] for r in rows])
    ratios = [r["length"] / r["full_length"] for r in rows
              if r["length"] is not None and r["full_length"]]
    return {"replans": len(rows), "windowed": sum(r["windowed"] for r in rows),
            "ms_median": round(float(np.median(ms)), 2),
            "ms_p90": round(float(np.percentile(ms, 90)), 2),
            "full_map_ms_median": round(float(np.median(full)), 2),
            "full_map_ms_p90": round(float(np.percentile(full, 90)), 2),
            "same_answer_share": round(float(np.mean([r["same_answer"] for r in rows])), 3),
            "path_length_ratio_median": round(float(np.median(ratios)), 3) if ratios else None,
            "path_length_ratio_max": round(float(max(ratios)), 3) if ratios else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--decisions", type=int, default=300, help="at most this many")
    ap.add_argument("--explorer", choices=["voronoi", "frontier"], default="voronoi")
    ap.add_argument("--lam", type=float, default=0.0, help="λ (the large-world case uses 0)")
    ap.add_argument("--world", type=Path, default=WORLD)
    ap.add_argument("--start", default="-5,20,0", help="spawn pose x,y,yaw")
    ap.add_argument("--step-m", type=float, default=math.inf,
                    help="move at most this far along each path (default: all of it)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    from sim.loader import load_world
    from sim.raycast import RayCaster

    world = load_world(args.world)
    mapper = Mapper(RayCaster(world.segments, world.circles), np.random.default_rng(args.seed))
    start = tuple(float(v) for v in args.start.split(","))
    assert len(start) == 3, "--start needs x,y,yaw"
    pose: tuple[float, float, float] = (start[0], start[1], start[2])
    params = ExplorerParams(lam=args.lam, total_area_m2=TOTAL_AREA_M2, coverage_threshold=0.9)
    explorer = make_explorer(args.explorer, params)
    visited = VisitedTargets(radius_m=1.0)
    mapper.scan(pose)
    decide_ms, analysis_ms, field_ms, astar_ms, known, reasons = [], [], [], [], [], {}
    replans: list[dict[str, Any]] = []
    travelled_m = 0.0
    finished = None
    for _ in range(args.decisions):
        grid = mapper.grid()
        t0 = time.perf_counter()
        out = explorer.decide(grid, pose, start, visited)
        decide_ms.append((time.perf_counter() - t0) * 1e3)
        known.append(float(np.mean(grid.data != UNKNOWN)))
        t0 = time.perf_counter()
        analysis = analyse(grid, params.analysis, include_xy=pose[:2])
        t1 = time.perf_counter()
        CostField(analysis.layer, pose[:2])
        t2 = time.perf_counter()
        analysis_ms.append((t1 - t0) * 1e3)
        field_ms.append((t2 - t1) * 1e3)
        if isinstance(out, Finished):
            finished = out.reason
            break
        assert isinstance(out, Decision)
        reasons[out.reason] = reasons.get(out.reason, 0) + 1
        try:
            t0 = time.perf_counter()
            plan(analysis.layer, pose[:2], out.target_xy, timeout_s=5.0)
            astar_ms.append((time.perf_counter() - t0) * 1e3)
        except PlanningError:
            pass
        poses = walk(out.path.xy_m, args.step_m, 0.5)
        for i, p in enumerate(poses):
            mapper.scan(p)
            if i == len(poses) // 2 and len(poses) >= 4:   # half way: the map has grown
                compare_replans(mapper.grid(), p, out.target_xy, explorer, replans)
        if poses:
            pose = poses[-1]
            travelled_m += min(args.step_m, out.path.length_m)
        if out.path.length_m <= args.step_m:
            visited.add(out.target_xy)

    def stats(v: list[float]) -> dict[str, float | None]:
        if not v:
            return {"median": None, "p90": None, "max": None}
        return {"median": round(float(np.median(v)), 2),
                "p90": round(float(np.percentile(v, 90)), 2), "max": round(float(max(v)), 2)}

    print(json.dumps({
        "world": args.world.name, "explorer": args.explorer, "lambda": args.lam,
        "grid_cells": [CELLS, CELLS], "resolution_m": RES_M,
        "decisions": len(decide_ms), "finished": finished, "reasons": reasons,
        "known_fraction_of_grid": [round(min(known), 4), round(max(known), 4)],
        "final_coverage": round(coverage(mapper.grid(), TOTAL_AREA_M2), 4),
        "path_travelled_m": round(travelled_m, 1),
        "decision_ms": stats(decide_ms), "analysis_ms": stats(analysis_ms),
        "dijkstra_ms": stats(field_ms), "astar_ms": stats(astar_ms),
        "replan": replan_figures(replans),
        "goal_median_ms": 100.0,
        "goal_met": bool(decide_ms) and float(np.median(decide_ms)) <= 100.0,
    }))


if __name__ == "__main__":
    main()
