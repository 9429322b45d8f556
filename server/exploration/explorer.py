"""Exploration decisions: where one robot goes next, and the path there.

Both explorers share one loop (:meth:`Explorer.decide`):

1. stop if the coverage threshold is reached (when the total area is known);
2. analyse the map: crop, cost layer, Voronoi skeleton, frontiers;
3. propose targets (the Voronoi explorer: rule-1 junctions, or frontier clusters when the
   skeleton offers none; the frontier explorer: frontier clusters);
4. settle path costs from the robot to every cell once (Dijkstra over the cost layer) and score
   every target; drop visited, reserved, lethal and unreachable ones;
5. take the cheapest and trace its path — or report that no reachable frontier remains.

``d_robot`` is the length [m] of the minimum-cost path from the robot (the Dijkstra path, which
costs the same as the A* path of :func:`server.planning.plan`); ``d_origin`` is the straight-line
distance [m] from the robot's start pose.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.exploration.analysis import AnalysisParams, MapAnalysis, analyse
from server.exploration.candidates import rule1_candidates
from server.exploration.coverage import coverage
from server.exploration.frontiers import Frontiers
from server.exploration.targets import TargetPlacer, reachable_mask
from server.exploration.visited import VisitedTargets
from server.exploration.walls import WallMemory
from server.planning.costmap import CostLayer
from server.planning.dijkstra import CostField
from server.planning.errors import StartOccupied
from server.planning.grid import OccupancyGrid
from server.planning.path import Path

log = logging.getLogger(__name__)

VORONOI, FRONTIER = "voronoi", "frontier"
OK, VISITED, RESERVED, AT_ROBOT, LETHAL, UNREACHABLE = (
    "ok", "visited", "reserved", "at robot", "lethal", "unreachable")
# LETHAL: no traversable cell near the target; UNREACHABLE: none that the robot can reach.


@dataclass(frozen=True)
class ExplorerParams:
    analysis: AnalysisParams = field(default_factory=AnalysisParams)
    # λ in C = λ·d_robot + (1−λ)·d_origin (Voronoi explorer).
    lam: float = 1.0
    # Coverage stop: when total_area_m2 is None the run stops when no reachable frontier remains.
    total_area_m2: float | None = None
    coverage_threshold: float = 0.98
    # Rule-1 junctions count as near a frontier within this distance.
    frontier_radius_m: float = 0.6
    # Junction targets move to the nearest cell the robot can reach within this distance.
    snap_radius_m: float = 0.5
    # A frontier cluster is approached from the reachable cell nearest to one of its cells,
    # at most this far from it (no wall in between).
    approach_radius_m: float = 1.0
    # Targets closer than this to the robot are where it already is.
    min_target_distance_m: float = 0.4
    # Targets within this distance of another robot's goal are reserved for it.
    reserve_radius_m: float = 2.0
    escape_radius_m: float = 0.5
    # True: score all target groups together (rule-1 junctions and frontier clusters compete on
    # cost); False: a later group only when no target of an earlier one is reachable (the
    # dissertation's order). None: pool when λ > 0. With λ = 0 the cost ignores where the robot
    # is, and pooled frontier clusters — they line the whole known region — would send it to
    # and fro between edges about as far from the start; junctions first damp that.
    pool_groups: bool | None = None
    # Voronoi explorer, one robot deciding: look across a frontier cluster from near its end
    # closest to the robot ("near_end"; a long frontier, e.g. a corridor seen at a grazing
    # angle, is resolved by a few steps there) or from near its middle ("middle").
    frontier_view: Literal["near_end", "middle"] = "near_end"

    @property
    def pooled(self) -> bool:
        return self.lam > 0 if self.pool_groups is None else self.pool_groups
    smooth: bool = True
    # Voronoi explorer: how often [s] the current target is looked at again (kept while
    # unexplored space still borders it, else a new decision) — about as often as the map is
    # redrawn. The Voronoi graph changes with the map: a junction in front of an open end moves
    # on as the sensor sees into it, and the frontier that made a target worth the trip is
    # often seen from metres away, long before the robot gets there.
    recheck_period_s: float = 1.0
    # Frontier explorer (explore_lite's defaults): cost = potential·d_robot − gain·size_m.
    potential_scale: float = 3.0
    gain_scale: float = 1.0


@dataclass(frozen=True)
class Target:
    """One scored candidate target."""

    xy: tuple[float, float]
    kind: str                 # VORONOI or FRONTIER
    status: str               # OK or why it was dropped
    d_robot_m: float = float("inf")
    d_origin_m: float = float("inf")
    cost: float = float("inf")
    frontier_size_m: float = 0.0


@dataclass(frozen=True, eq=False)
class Decision:
    target_xy: tuple[float, float]
    path: Path
    reason: str               # which rule produced the target
    candidates: tuple[Target, ...]
    coverage: float | None


@dataclass(frozen=True)
class Finished:
    """Nothing left to explore: the coverage threshold is reached, or no reachable frontier
    remains (``candidates`` then says why each one was dropped)."""

    reason: str
    coverage: float | None
    candidates: tuple[Target, ...] = field(default=())


@dataclass
class _Proposal:
    rc: NDArray[np.int64]                 # (K, 2) target cells in the analysed grid
    kind: str
    size_cells: NDArray[np.int64] | None = None
    # Frontier clusters the targets stand for (then placed by approach, not snapping).
    frontiers: Frontiers | None = None
    # Per target: the reachable cell the robot goes to (None: there is none near it).
    snapped: list[tuple[int, int] | None] = field(default_factory=list)

    def place(self, placer: TargetPlacer, params: ExplorerParams,
              toward_rc: NDArray[np.float64] | None = None) -> _Proposal:
        if self.frontiers is not None:
            self.snapped = placer.frontiers(self.frontiers, params.approach_radius_m, toward_rc)
        else:
            self.snapped = placer.points(self.rc, params.snap_radius_m)
        return self

    def targets_xy(self, layer: CostLayer) -> NDArray[np.float64]:
        """World positions of the targets (placed where possible)."""
        cells = [s if s is not None else (int(rc[0]), int(rc[1]))
                 for s, rc in zip(self.snapped, self.rc, strict=True)]
        return layer.geometry.cell_to_world(np.asarray(cells, np.int64).reshape(-1, 2))


@dataclass(frozen=True, eq=False)
class TeamCosts:
    targets_xy: NDArray[np.float64]         # (K, 2)
    cost: NDArray[np.float64]               # (R, K), ∞ = not a choice for that robot
    kind: str
    fields: list[CostField | None]
    smooth: bool

    def path(self, robot: int, target: int) -> Path:
        f = self.fields[robot]
        if f is None:
            raise StartOccupied(f"robot {robot} has no cost field (its start is lethal)")
        return f.path_to(self.targets_xy[target], smooth=self.smooth)


class Explorer(ABC):
    """Shared decision loop; subclasses propose and score targets."""

    name = "base"

    def __init__(self, params: ExplorerParams | None = None) -> None:
        self.params = params or ExplorerParams()
        #: cells once seen occupied, kept off frontiers (see :mod:`server.exploration.walls`)
        self.walls_seen = WallMemory()

    # Whether ``params.frontier_view`` applies (the frontier baseline keeps the middle).
    views_frontiers_from_near_end = False

    @property
    def recheck_period_s(self) -> float | None:
        """How often [s] a navigator should look at its current target again (None: its own
        replanning period)."""
        return None

    def analyse(self, grid: OccupancyGrid, include_xy: ArrayLike,
                visited: VisitedTargets | None = None) -> MapAnalysis:
        """The map analysis this explorer decides on (remembering the grid's walls first)."""
        self.walls_seen.update(grid)
        return analyse(grid, self.params.analysis, include_xy=include_xy,
                       seen_xy=None if visited is None else visited.points_xy,
                       walls_seen=self.walls_seen)

    def decide(self, grid: OccupancyGrid, robot_pose: ArrayLike, start_pose: ArrayLike,
               visited: VisitedTargets, *,
               reserved_xy: ArrayLike = ()) -> Decision | Finished:
        """Next target and path for a robot at ``robot_pose`` (x, y, θ) that started at
        ``start_pose``; ``reserved_xy`` are other robots' goals (targets near them are skipped).

        Raises :class:`server.planning.StartOccupied` when the robot is inside the lethal zone
        with nothing traversable within the escape radius (the caller recovers, then retries).
        """
        p = self.params
        robot_xy = np.asarray(robot_pose, np.float64).reshape(-1)[:2]
        start_xy = np.asarray(start_pose, np.float64).reshape(-1)[:2]
        cov = coverage(grid, p.total_area_m2) if p.total_area_m2 else None
        if cov is not None and cov >= p.coverage_threshold:
            return Finished(f"coverage {cov:.3f} reached the threshold {p.coverage_threshold}",
                            cov)
        analysis = self.analyse(grid, robot_xy, visited)
        if len(analysis.frontiers) == 0:
            return Finished("no frontier left", cov)
        proposals = self._placed_proposals(analysis, [robot_xy])
        # Dijkstra stops once every target still worth a look is settled.
        goals = np.concatenate([pr.targets_xy(analysis.layer) for pr in proposals])
        goals = goals[~visited.mask(goals)]
        field_ = CostField(analysis.layer, robot_xy, goals_xy=goals if len(goals) else None,
                           escape_radius_m=p.escape_radius_m)
        targets: list[Target] = []
        ok: list[Target] = []
        for proposal in proposals:
            scored = self._score(analysis, field_, proposal, robot_xy, start_xy, visited,
                                 np.asarray(reserved_xy, np.float64).reshape(-1, 2))
            targets.extend(scored)
            ok.extend(t for t in scored if t.status == OK)
            if ok and not p.pooled:
                break
        if ok:
            best = min(ok, key=lambda t: t.cost)  # the earlier group wins a tie
            path = field_.path_to(best.xy, smooth=p.smooth)
            return Decision(best.xy, path, best.kind, tuple(targets), cov)
        return Finished("no reachable frontier", cov, tuple(targets))

    def team_costs(self, grid: OccupancyGrid, robot_poses: Sequence[ArrayLike],
                   start_poses: Sequence[ArrayLike], visited: VisitedTargets) -> TeamCosts:
        """Targets and a cost matrix robots × targets for a team sharing ``grid`` (one frame),
        for :func:`server.exploration.assignment.assign_optimal` or ``assign_separated``.

        Groups of targets (rule-1 junctions, frontier clusters) are pooled or tried in order,
        as in ``decide``; a robot that cannot be planned from (StartOccupied) gets a row of ∞.
        """
        p = self.params
        robots = np.asarray(robot_poses, np.float64).reshape(-1, 3)[:, :2]
        starts = np.asarray(start_poses, np.float64).reshape(-1, 3)[:, :2]
        analysis = self.analyse(grid, robots, visited)
        fields: list[CostField | None] = []
        for xy in robots:
            try:
                fields.append(CostField(analysis.layer, xy, escape_radius_m=p.escape_radius_m))
            except StartOccupied as e:
                log.warning("robot at %s left out of the assignment: %s", xy, e)
                fields.append(None)
        none = np.zeros((0, 2))
        placed = self._placed_proposals(analysis, list(robots)) if len(analysis.frontiers) else []
        groups: list[tuple[NDArray[np.float64], NDArray[np.float64], str]] = []
        for proposal in placed:
            rows: list[list[Target]] = []
            for i, f in enumerate(fields):
                rows.append([] if f is None else self._score(
                    analysis, f, proposal, robots[i], starts[i], visited, none))
            n = max(len(r) for r in rows)
            if n == 0:
                continue
            cost = np.full((len(robots), n), np.inf)
            targets_xy = np.zeros((n, 2))
            for i, row in enumerate(rows):
                for k, t in enumerate(row):
                    targets_xy[k] = t.xy
                    if t.status == OK:
                        cost[i, k] = t.cost
            if not np.isfinite(cost).any():
                continue
            if not p.pooled:  # the first group with a reachable target, as ``decide`` does
                return TeamCosts(targets_xy, cost, proposal.kind, fields, p.smooth)
            groups.append((targets_xy, cost, proposal.kind))
        if groups:  # pooled: every group's targets compete on one cost, as in ``decide``
            return TeamCosts(np.concatenate([g[0] for g in groups]),
                             np.concatenate([g[1] for g in groups], axis=1),
                             "+".join(g[2] for g in groups), fields, p.smooth)
        return TeamCosts(none, np.zeros((len(robots), 0)), "", fields, p.smooth)

    def _placed_proposals(self, analysis: MapAnalysis,
                          robots_xy: list[NDArray[np.float64]]) -> list[_Proposal]:
        reach = reachable_mask(analysis.layer, robots_xy, self.params.escape_radius_m)
        placer = TargetPlacer(analysis.layer, reach, analysis.grid.occupied)
        toward = (analysis.layer.geometry.world_to_cell(robots_xy[0]).astype(np.float64)
                  if self.views_frontiers_from_near_end and self.params.frontier_view == "near_end"
                  and len(robots_xy) == 1 else None)
        return [pr.place(placer, self.params, toward) for pr in self._proposals(analysis)]

    @abstractmethod
    def _proposals(self, analysis: MapAnalysis) -> list[_Proposal]:
        """Groups of targets: scored together (``pool_groups``), or tried in order — a later
        group only when no earlier one has a reachable target."""

    @abstractmethod
    def _target_cost(self, d_robot_m: float, d_origin_m: float, size_m: float) -> float:
        """Score of a reachable target (the cheapest is chosen)."""

    def _score(self, analysis: MapAnalysis, field_: CostField, proposal: _Proposal,
               robot_xy: NDArray[np.float64], start_xy: NDArray[np.float64],
               visited: VisitedTargets, reserved_xy: NDArray[np.float64]) -> list[Target]:
        p = self.params
        layer = analysis.layer
        res = layer.geometry.resolution_m
        out: list[Target] = []
        sizes = (proposal.size_cells if proposal.size_cells is not None
                 else np.zeros(len(proposal.rc), np.int64))
        snapped = proposal.snapped
        xy_all = proposal.targets_xy(layer)
        is_visited = visited.mask(xy_all)
        for i, xy in enumerate(xy_all):
            t_xy = (float(xy[0]), float(xy[1]))
            size_m = float(sizes[i]) * res
            d_origin = float(np.hypot(*(xy - start_xy)))
            status = OK
            if snapped[i] is None:
                # out of reach: walled off from the robot, or no traversable cell near at all
                r, c = (int(v) for v in proposal.rc[i])
                radius = (p.approach_radius_m if proposal.frontiers is not None
                          else p.snap_radius_m)
                status = LETHAL if layer.escape((r, c), radius) is None else UNREACHABLE
            elif is_visited[i]:
                status = VISITED
            elif len(reserved_xy) and np.min(np.hypot(*(reserved_xy - xy).T)) < p.reserve_radius_m:
                status = RESERVED
            elif np.hypot(*(xy - robot_xy)) < p.min_target_distance_m:
                status = AT_ROBOT
            if status != OK:
                out.append(Target(t_xy, proposal.kind, status, d_origin_m=d_origin,
                                  frontier_size_m=size_m))
                continue
            d_robot = field_.length_m(xy)
            if not np.isfinite(d_robot):
                out.append(Target(t_xy, proposal.kind, UNREACHABLE, d_origin_m=d_origin,
                                  frontier_size_m=size_m))
                continue
            out.append(Target(t_xy, proposal.kind, OK, d_robot, d_origin,
                              self._target_cost(d_robot, d_origin, size_m), size_m))
        return out


class VoronoiExplorer(Explorer):
    """Rule-1 Voronoi junctions near frontiers, scored C = λ·d_robot + (1−λ)·d_origin; frontier
    clusters (same score) when no junction qualifies."""

    name = VORONOI
    views_frontiers_from_near_end = True

    @property
    def recheck_period_s(self) -> float | None:
        return self.params.recheck_period_s

    def _proposals(self, analysis: MapAnalysis) -> list[_Proposal]:
        res = analysis.layer.geometry.resolution_m
        nodes = rule1_candidates(analysis.graph, analysis.frontiers,
                                 self.params.frontier_radius_m / res)
        fr = analysis.frontiers
        return [_Proposal(analysis.graph.node_rc[nodes], VORONOI),
                _Proposal(fr.middle_rc, FRONTIER, fr.size_cells, fr)]

    def _target_cost(self, d_robot_m: float, d_origin_m: float, size_m: float) -> float:
        lam = self.params.lam
        return lam * d_robot_m + (1.0 - lam) * d_origin_m


class FrontierExplorer(Explorer):
    """Nearest-frontier baseline (the explore_lite strategy): frontier clusters scored
    potential_scale·d_robot − gain_scale·size_m; visited/blacklisted ones skipped."""

    name = FRONTIER

    def _proposals(self, analysis: MapAnalysis) -> list[_Proposal]:
        fr = analysis.frontiers
        return [_Proposal(fr.middle_rc, FRONTIER, fr.size_cells, fr)]

    def _target_cost(self, d_robot_m: float, d_origin_m: float, size_m: float) -> float:
        return self.params.potential_scale * d_robot_m - self.params.gain_scale * size_m


def make_explorer(name: str, params: ExplorerParams | None = None) -> Explorer:
    """``"voronoi"`` or ``"frontier"``."""
    kinds: dict[str, type[Explorer]] = {VORONOI: VoronoiExplorer, FRONTIER: FrontierExplorer}
    if name not in kinds:
        raise ValueError(f"unknown explorer {name!r}; choose one of {sorted(kinds)}")
    return kinds[name](params)
