"""Verified loop closures into a robot's graph, and out again where the graph disagrees.

``LoopCloser`` (``server.slam.loop_closure``) finds and verifies closures one keyframe at a
time; a verified one can still be wrong (a corridor like another). Each goes in as a
between-factor under a Huber kernel, so a wrong one pulls less than its σ would; once the
graph has settled, one whose whitened error is still implausible (χ² > ``loop.max_chi2``) is
taken out, and the graph settles again without it. A kept closure is also a short edge of the
loop closer's path graph: the uncertainty it measures distances by shrinks across it.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from factors.scan_match import loop_closure_factor, whitened_chi2
from server.slam.backend import (
    FactorRecord,
    PoseGraph,
    RobotTrajectory,
    add_constraint,
    drop_constraint,
)
from server.slam.config import GraphConfig, LoopClosureConfig
from server.slam.loop_closure import LOOP_EDGE_LENGTH_M, LoopCloser, LoopClosure

log = logging.getLogger(__name__)


def add_loop_closures(graph: PoseGraph, trajectory: RobotTrajectory, loops: LoopCloser,
                      closures: list[LoopClosure], cfg: LoopClosureConfig,
                      graph_cfg: GraphConfig) -> tuple[int, int]:
    """Add ``closures`` (σ the match's times ``sigma_scale``, floored as a scan match's),
    optimise ``extra_iterations_after_loop`` times, and take out the implausible ones (see
    the module). Returns how many were kept and how many taken out."""
    floor = np.array([graph_cfg.match_sigma_floor_m, graph_cfg.match_sigma_floor_m,
                      math.radians(graph_cfg.match_sigma_floor_deg)])
    added: list[tuple[LoopClosure, FactorRecord]] = []
    for lc in closures:
        f = loop_closure_factor(trajectory.key(lc.anchor), trajectory.key(lc.keyframe),
                                lc.T_anchor_kf, lc.information, cfg.sigma_scale ** 2, floor,
                                "huber", cfg.huber_k)
        added.append((lc, add_constraint(graph, trajectory, f, "loop")))
    graph.iterate(graph_cfg.extra_iterations_after_loop)
    est = graph.estimate()
    kept = removed = 0
    for lc, rec in added:
        chi2 = whitened_chi2(rec.factor, est)
        if chi2 > cfg.max_chi2:
            log.info("loop closure %d-%d removed: χ² %.1f after optimisation",
                     lc.anchor, lc.keyframe, chi2)
            drop_constraint(graph, trajectory, rec)
            loops.stats.removed_inconsistent += 1
            removed += 1
        else:
            loops.add_edge(lc.anchor, lc.keyframe, LOOP_EDGE_LENGTH_M)
            kept += 1
    if removed:
        graph.iterate(graph_cfg.extra_iterations_after_loop)
    return kept, removed
