"""Autonomous exploration: Voronoi skeleton, rule-1 targets, frontiers, coverage, assignment.

    explorer = make_explorer("voronoi", ExplorerParams(lam=1.0, total_area_m2=400))
    outcome = explorer.decide(grid, robot_pose, start_pose, visited)
    if isinstance(outcome, Finished): ...          # threshold reached / no reachable frontier
    else: follow(outcome.path)                      # Decision
"""

from server.exploration.analysis import AnalysisParams, MapAnalysis, analyse
from server.exploration.assignment import assign_optimal, assign_separated, assign_spread
from server.exploration.candidates import rule1_candidates, rule1_junctions
from server.exploration.coverage import coverage, coverage_reached, explored_area_m2
from server.exploration.explorer import (
    Decision,
    Explorer,
    ExplorerParams,
    Finished,
    FrontierExplorer,
    Target,
    TeamCosts,
    VoronoiExplorer,
    make_explorer,
)
from server.exploration.frontiers import (
    Frontiers,
    cluster_frontiers,
    find_frontiers,
    frontier_mask,
)
from server.exploration.skeleton import SkeletonGraph, skeleton_graph, voronoi_skeleton
from server.exploration.visited import VisitedTargets

__all__ = [
    "AnalysisParams",
    "Decision",
    "Explorer",
    "ExplorerParams",
    "Finished",
    "FrontierExplorer",
    "Frontiers",
    "MapAnalysis",
    "SkeletonGraph",
    "Target",
    "TeamCosts",
    "VisitedTargets",
    "VoronoiExplorer",
    "analyse",
    "assign_optimal",
    "assign_separated",
    "assign_spread",
    "cluster_frontiers",
    "coverage",
    "coverage_reached",
    "explored_area_m2",
    "find_frontiers",
    "frontier_mask",
    "make_explorer",
    "rule1_candidates",
    "rule1_junctions",
    "skeleton_graph",
    "voronoi_skeleton",
]
