"""Replanning and deciding, as jobs that can run in another process.

A robot re-plans its path to its target about once a second while it drives (the map has grown
since), and chooses a new target when it reaches one: the map analysis (cost layer, skeleton,
frontiers) and the path searches cost tens of milliseconds, more than everything else the server
does for a scan. A :class:`Replan`, like the arguments of :func:`decide`, holds everything the
work needs and nothing of the server's state, so a pool of processes can do it while the server
goes on with other scans (a robot that decides alone stands meanwhile; a team's decisions,
which weigh every teammate, stay on the server's thread).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from server.exploration.analysis import AnalysisParams, analyse
from server.exploration.walls import WallMemory
from server.planning import OccupancyGrid, PlanningError, plan

if TYPE_CHECKING:
    from server.exploration import Decision, Explorer, Finished, VisitedTargets

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Replan:
    """A fresh path from ``pose_xy`` to ``target_xy`` while the target still borders
    unexplored space (a frontier within ``commit_radius_m``)."""

    grid: OccupancyGrid
    params: AnalysisParams
    walls: WallMemory
    pose_xy: tuple[float, float]
    target_xy: tuple[float, float]
    commit_radius_m: float


@dataclass(frozen=True)
class Replanned:
    """The job's answer: the path, or None with the reason the target is no longer kept."""

    target_xy: tuple[float, float]
    path_xy: F64 | None
    reason: str = ""
    planning_failed: bool = False    # no path found (not: the target is no longer open)


#: A replan looks at the map around the robot and its target first: the box of both, widened
#: by this much, by half their distance and by the commit radius. Only if no path is found
#: there does it look at the whole map. Its cost then follows the distance to the target, not
#: the size of the explored map (a 50 × 50 m house is 750 × 750 cells).
WINDOW_MARGIN_M = 4.0
#: a window larger than this share of the map is not worth cutting out
WINDOW_MAX_SHARE = 0.5


def replan(job: Replan) -> Replanned:
    window = replan_window(job)
    if window is not None:
        answer = _replan_on(window, job)
        if answer.path_xy is not None or not answer.planning_failed:
            return answer   # (whether the target still borders unexplored space is settled
    return _replan_on(job.grid, job)   # within the window, which holds its commit radius)


def replan_window(job: Replan) -> OccupancyGrid | None:
    """The part of ``job.grid`` a replan looks at first, or None: the whole map."""
    p, t = np.asarray(job.pose_xy, np.float64), np.asarray(job.target_xy, np.float64)
    m = WINDOW_MARGIN_M + 0.5 * float(np.hypot(*(p - t))) + job.commit_radius_m
    g = job.grid
    (r0, c0), (r1, c1) = g.geometry.world_to_cell(np.stack([np.minimum(p, t) - m,
                                                            np.maximum(p, t) + m]))
    H, W = g.data.shape
    r0, c0, r1, c1 = max(0, int(r0)), max(0, int(c0)), min(H, int(r1) + 1), min(W, int(c1) + 1)
    if r1 <= r0 or c1 <= c0 or (r1 - r0) * (c1 - c0) > WINDOW_MAX_SHARE * H * W:
        return None
    return g.crop(r0, r1, c0, c1)


def _replan_on(grid: OccupancyGrid, job: Replan) -> Replanned:
    analysis = analyse(grid, job.params, include_xy=np.asarray(job.pose_xy),
                       seen_xy=None, walls_seen=job.walls)
    fr = analysis.frontiers
    if len(fr) == 0:
        return Replanned(job.target_xy, None, "no frontier left")
    geo = analysis.layer.geometry
    d = np.hypot(*(geo.cell_to_world(fr.cells_rc) - np.asarray(job.target_xy)).T)
    if d.min() > job.commit_radius_m:
        return Replanned(job.target_xy, None, "no longer borders unexplored space")
    try:
        path = plan(analysis.layer, job.pose_xy, job.target_xy)
    except PlanningError as e:
        return Replanned(job.target_xy, None, str(e), planning_failed=True)
    return Replanned(job.target_xy, path.xy_m)


@dataclass(frozen=True)
class Decided:
    """A decision's outcome (or the planning error that prevented it), how long it took, and
    the walls the explorer remembered making it."""

    outcome: Decision | Finished | PlanningError
    ms: float
    walls: WallMemory


def decide(explorer: Explorer, grid: OccupancyGrid, pose: F64, start_pose: F64,
           visited: VisitedTargets, reserved_xy: F64) -> Decided:
    """``explorer.decide``, its planning errors returned rather than raised (here or in a
    pool process, where ``explorer`` is a copy)."""
    t0 = time.perf_counter()
    outcome: Decision | Finished | PlanningError
    try:
        outcome = explorer.decide(grid, pose, start_pose, visited, reserved_xy=reserved_xy)
    except PlanningError as e:
        outcome = e
    return Decided(outcome, (time.perf_counter() - t0) * 1e3, explorer.walls_seen)
