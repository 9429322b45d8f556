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


def replan(job: Replan) -> Replanned:
    analysis = analyse(job.grid, job.params, include_xy=np.asarray(job.pose_xy),
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
        return Replanned(job.target_xy, None, str(e))
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
