"""Each robot's parts, built from the server's configuration in one place.

The configuration models say what a user sets; the algorithm packages take small parameter
dataclasses of their own (they are also used without a server). This module is the one place
that turns the first into the second: a navigator (explorer, pure pursuit, VFH, stuck
detection), a lookout (a null one when the server does not look at movers), a SLAM pipeline,
a team's grid mapper and the merge verifier.
"""

from __future__ import annotations

import math

from server.config import ServerConfig
from server.control import PursuitParams, StuckDetector, VfhParams
from server.exploration import ExplorerParams, VisitedTargets, make_explorer
from server.exploration.analysis import AnalysisParams
from server.exploration.navigator import Navigator
from server.lookout import Lookout, LookParams, NullLookout
from server.planning import CostParams
from server.rendezvous.evidence import MergeVerifier, VerifierParams
from server.slam import RobotSlam
from server.slam.grid import GridParams
from server.slam.mapping import GridMapper


class Stages:
    """Factories of a robot's navigator, lookout and SLAM, and of a team's mapper."""

    def __init__(self, cfg: ServerConfig) -> None:
        self.cfg = cfg
        e, c, t = cfg.explore, cfg.control, cfg.teams
        analysis = AnalysisParams(cost=CostParams(robot_radius_m=c.robot_radius_m,
                                                  unknown_is_obstacle=e.unknown_as_obstacle))
        #: shared by every robot's explorer until the λ schedule gives one its own
        self.explorer_params = ExplorerParams(
            analysis=analysis, lam=e.lam, total_area_m2=e.total_area_m2,
            coverage_threshold=e.coverage_threshold, frontier_view=e.frontier_view)
        self.look_params = LookParams(
            max_range_m=t.max_sighting_range_m, omega_rps=min(1.0, c.omega_max_rps),
            approach_range_m=t.approach_range_m, approach_v_mps=c.v_mps,
            approach_stop_m=min(1.2, 0.7 * t.max_sighting_range_m))
        #: σ of a robot's pose at a sighting (x, y [m], θ [rad]) in the direct method
        self.pose_sigmas = (t.pose_sigma_m, t.pose_sigma_m, math.radians(t.pose_sigma_deg))
        self.looks = t.enabled and t.look_at_movers

    def navigator(self) -> Navigator:
        c = self.cfg.control
        return Navigator(
            make_explorer(self.cfg.explore.explorer, self.explorer_params),
            PursuitParams(lookahead_m=c.lookahead_m, v_mps=c.v_mps, omega_max_rps=c.omega_max_rps,
                          goal_tolerance_m=c.goal_tolerance_m),
            VfhParams(robot_radius_m=c.robot_radius_m, v_mps=c.v_mps,
                      omega_max_rps=c.omega_max_rps) if c.vfh else None,
            StuckDetector(c.stuck_window_s, c.stuck_min_progress_m),
            self.cfg.explore.replan_period_s)

    def lookout(self, robot_id: str) -> Lookout:
        """Turning toward movers and approaching them; a null lookout when teams are off or
        the server does not look at movers."""
        return Lookout(self.look_params, robot_id) if self.looks else NullLookout()

    def slam(self, symbol: str, key_block: int) -> RobotSlam:
        return RobotSlam(symbol, self.cfg.slam, key_block=key_block)

    def mapper(self) -> GridMapper:
        return GridMapper(GridParams(**self.cfg.slam.grid.model_dump()))

    def visited(self) -> VisitedTargets:
        return VisitedTargets(self.cfg.explore.visited_radius_m)

    def verifier(self) -> MergeVerifier:
        t = self.cfg.teams
        return MergeVerifier(VerifierParams(min_sightings=t.min_sightings, window_s=t.window_s))
