"""Where one robot goes and how: exploration target, path, pure pursuit, VFH, recovery.

``Navigator.step`` is called once per scan with the robot's SLAM pose and returns the velocity
command. It decides a new target when it has none, when the last one was reached, when a
replanning period has passed (the map has grown since) and the target no longer borders
unexplored space, or after a recovery manoeuvre. The explorer may ask for a shorter period.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from server.control import (
    STOP,
    Driver,
    Obstacles,
    PurePursuit,
    PursuitParams,
    Recovery,
    StuckDetector,
    Twist,
    Vfh,
    VfhParams,
    limit,
)
from server.exploration import Decision, Explorer, Finished, VisitedTargets
from server.exploration.replan import Decided, Replan, Replanned, decide, replan
from server.planning import OccupancyGrid, PlanningError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

class NavMode(StrEnum):
    """What a robot's navigator is doing (the values are the wire's ``RobotEstimate.mode``)."""

    WAITING = "waiting"        # no target yet (or deciding)
    EXPLORING = "exploring"    # following a path to a target
    RECOVERING = "stuck"       # backing out after being stuck
    DONE = "done"              # its team finished, or no reachable frontier is left


WAITING, EXPLORING, RECOVERING, DONE = (NavMode.WAITING, NavMode.EXPLORING, NavMode.RECOVERING,
                                        NavMode.DONE)


@dataclass
class NavStats:
    decisions: int = 0
    decision_failures: int = 0
    targets_reached: int = 0
    recoveries: int = 0
    decision_ms: list[float] = field(default_factory=list)


class Navigator:
    """Target selection and motion control of one robot (no I/O)."""

    def __init__(self, explorer: Explorer, pursuit: PursuitParams, vfh: VfhParams | None,
                 stuck: StuckDetector, replan_period_s: float,
                 commit_radius_m: float = 1.5) -> None:
        self.explorer = explorer
        self._own_explorer = explorer      # ``explorer`` may wrap it (a team's coordination)
        self.pursuit = PurePursuit(pursuit)
        #: makes every twist this navigator sends (``server.control.driver``)
        self.driver = Driver(Vfh(vfh) if vfh is not None else None)
        self.stuck = stuck
        self.recovery = Recovery()
        self.replan_period_s = replan_period_s
        self.commit_radius_m = commit_radius_m
        self.mode: NavMode = WAITING
        self.target_xy: tuple[float, float] | None = None
        self.path_xy: F64 | None = None
        self.finished_reason = ""
        self.stats = NavStats()
        self._last_decision_s = -np.inf
        self._looked_around = False
        self._spin_until_s = -np.inf
        self._replanning: Future[Replanned] | None = None
        self._deciding: Future[Decided] | None = None

    def __getstate__(self) -> dict[str, object]:
        state = dict(self.__dict__)
        state["_replanning"] = None      # a job in flight is asked again after a restart
        state["_deciding"] = None
        return state

    def step(self, now_s: float, pose: F64, start_pose: F64, obstacles: Obstacles,
             grid: Callable[[], OccupancyGrid], visited: VisitedTargets,
             reserved_xy: F64 | None = None,
             planner: Executor | None = None) -> Twist:
        """The command for this scan. ``grid`` is called only when a decision is due.
        ``planner``: where replanning to a kept target runs while the robot follows its
        current path, and the decisions of a robot that decides alone (not in a team) while
        it stands; None: here, before the command."""
        if self.mode == DONE:
            return STOP
        if now_s < self._spin_until_s:
            return limit(Twist(0.0, self.pursuit.params.omega_max_rps))   # looking round
        if self.recovery.active:
            twist = self.recovery.command(now_s)
            if twist is not None:
                return limit(twist)     # the manoeuvre's own: away from what it hit
            self.stuck.reset()
            self._last_decision_s = -np.inf  # decide afresh after the manoeuvre
        if self.path_xy is not None and self.stuck.update(now_s, pose):
            log.info("stuck near %s; recovering and dropping the target", pose[:2].round(2))
            self._give_up_target(visited)
            self.stats.recoveries += 1
            self.recovery.start(now_s, obstacles.points_xy)
            self.mode = RECOVERING
            return limit(self.recovery.command(now_s) or STOP)
        if self._deciding is not None:
            if not self._deciding.done():
                return STOP                   # the decision is being made elsewhere
            decided, self._deciding = self._deciding, None
            self._take_decision(now_s, decided)
            if self.mode == DONE or self.recovery.active or now_s < self._spin_until_s:
                return STOP
        if self._replanning is not None and self._replanning.done():
            job, self._replanning = self._replanning, None
            if not self._take_replan(job):
                self._decide(now_s, pose, start_pose, grid(), visited, reserved_xy, planner)
        if self.path_xy is None and self._deciding is None:
            self._decide(now_s, pose, start_pose, grid(), visited, reserved_xy, planner)
        elif (self.path_xy is not None and self._replanning is None
              and now_s - self._last_decision_s >= self._recheck_period_s()):
            # the map has grown: keep the target while it still borders unexplored space
            # (switching between near-equal targets makes a robot dither), else choose again
            g = grid()
            if not self._replan_to_target(now_s, pose, g, planner):
                self._decide(now_s, pose, start_pose, g, visited, reserved_xy, planner)
        if self.mode == DONE or self.path_xy is None:
            return STOP
        assert self.path_xy is not None
        drive = self.driver.follow(self.pursuit, pose, self.path_xy, obstacles)
        if drive.reached:
            self.stats.targets_reached += 1
            if self.target_xy is not None:
                visited.add(self.target_xy)
            self.path_xy, self.target_xy = None, None
            self._decide(now_s, pose, start_pose, grid(), visited, reserved_xy, planner)
            if self.path_xy is None:
                return STOP
            drive = self.driver.follow(self.pursuit, pose, self.path_xy, obstacles)
        return drive.twist

    def _recheck_period_s(self) -> float:
        """The replanning period, or the explorer's shorter one for looking at its target."""
        own = self.explorer.recheck_period_s
        return self.replan_period_s if own is None else min(self.replan_period_s, own)

    def _decide(self, now_s: float, pose: F64, start_pose: F64, grid: OccupancyGrid,
                visited: VisitedTargets, reserved_xy: F64 | None,
                planner: Executor | None = None) -> None:
        self._last_decision_s = now_s
        reserved = np.zeros((0, 2)) if reserved_xy is None else np.asarray(reserved_xy)
        if planner is not None and self.explorer is self._own_explorer:
            # alone, the decision depends on nothing but what goes with it: the robot stands
            # while another process makes it
            self.path_xy = None
            try:
                self._deciding = planner.submit(decide, self._own_explorer, grid, pose.copy(),
                                                start_pose.copy(), visited, reserved)
                return
            except RuntimeError as e:
                log.warning("deciding here: the planner pool is gone (%s)", e)
        self._apply_decision(now_s, decide(self.explorer, grid, pose, start_pose, visited,
                                           reserved))

    def _take_decision(self, now_s: float, job: Future[Decided]) -> None:
        try:
            answer = job.result()
        except Exception as e:      # a pool process died: decide again at the next step
            log.warning("a decision job failed: %s", e)
            self._last_decision_s = -np.inf
            return
        if self.explorer is not self._own_explorer:   # joined a team meanwhile
            return
        self._own_explorer.walls_seen = answer.walls   # what it remembered deciding
        self._apply_decision(now_s, answer)

    def _apply_decision(self, now_s: float, answer: Decided) -> None:
        self.stats.decision_ms.append(answer.ms)
        outcome = answer.outcome
        if isinstance(outcome, PlanningError):
            # e.g. the robot stands inside the inflated zone of a wall: back off, retry
            log.info("no decision: %s", outcome)
            self.stats.decision_failures += 1
            self.path_xy = None
            self.recovery.start(now_s, np.zeros((0, 2)))
            self.mode = RECOVERING
            return
        self.stats.decisions += 1
        if isinstance(outcome, Finished):
            self.path_xy = self.target_xy = None
            p = self.explorer.params
            reached = outcome.coverage is not None and outcome.coverage >= p.coverage_threshold
            if not reached and not self._looked_around:
                # nothing left in view: turn once on the spot before believing it
                self._looked_around = True
                self._spin_until_s = now_s + 2 * np.pi / self.pursuit.params.omega_max_rps
                self.mode = RECOVERING
                return
            self.mode, self.finished_reason = DONE, outcome.reason
            log.info("exploration finished: %s", outcome.reason)
            return
        self._looked_around = False
        assert isinstance(outcome, Decision)
        if outcome.target_xy != self.target_xy:
            self.pursuit.reset()
            self.stuck.reset()
        self.mode = EXPLORING
        self.target_xy = outcome.target_xy
        self.path_xy = outcome.path.xy_m

    def _replan_to_target(self, now_s: float, pose: F64, grid: OccupancyGrid,
                          planner: Executor | None = None) -> bool:
        """A fresh path to the current target if it is still open; False when it is not.
        With a ``planner`` the job is handed to it and the robot keeps its path meanwhile
        (True); the answer is taken at a later step."""
        if self.target_xy is None:
            return False
        self._last_decision_s = now_s
        explorer = self._own_explorer
        explorer.walls_seen.update(grid)
        job = Replan(grid, explorer.params.analysis, explorer.walls_seen,
                     (float(pose[0]), float(pose[1])), self.target_xy, self.commit_radius_m)
        if planner is not None:
            try:
                self._replanning = planner.submit(replan, job)
                return True
            except RuntimeError as e:    # the pool is shutting down or broken: plan here
                log.warning("replanning here: the planner pool is gone (%s)", e)
        return self._apply_replan(replan(job))

    def _take_replan(self, job: Future[Replanned]) -> bool:
        try:
            return self._apply_replan(job.result())
        except Exception as e:      # a pool process died: choose again here
            log.warning("a replanning job failed: %s", e)
            return False

    def _apply_replan(self, answer: Replanned) -> bool:
        if answer.target_xy != self.target_xy or self.mode != EXPLORING:
            return self.path_xy is not None   # the target changed meanwhile: keep the new one
        if answer.path_xy is None:
            log.info("target %s dropped: %s", self.target_xy, answer.reason)
            return False
        self.path_xy = answer.path_xy
        return True

    def _give_up_target(self, visited: VisitedTargets) -> None:
        if self.target_xy is not None:
            visited.add(self.target_xy)  # do not pick the same unreachable target again
        self.path_xy, self.target_xy = None, None
        self.pursuit.reset()

    def resume(self) -> None:
        """Explore again after ``finish`` (the team it finished with was split up)."""
        if self.mode == DONE:
            self.mode, self.finished_reason = WAITING, ""
            self._looked_around = False
            self._last_decision_s = -np.inf

    def finish(self, reason: str) -> None:
        self.mode, self.finished_reason = DONE, reason
        self._deciding = self._replanning = None
        self.path_xy = self.target_xy = None

    # -- what others may change --------------------------------------------------------------
    @property
    def own_explorer(self) -> Explorer:
        """The robot's own explorer (under its team's, when it is in a team of several)."""
        return self._own_explorer

    def use_explorer(self, explorer: Explorer) -> None:
        """Decide targets with ``explorer`` from now on: the robot's own, or a team's that
        wraps it."""
        self.explorer = explorer

    def set_lam(self, lam: float) -> None:
        """λ of the robot's own explorer."""
        base = self._own_explorer
        if base.params.lam != lam:
            base.params = dataclasses.replace(base.params, lam=lam)

    def drop_target(self) -> None:
        """Forget the current target and path (e.g. the map frame changed under them)."""
        self._deciding = self._replanning = None
        self.target_xy = None
        self.path_xy = None
        self.pursuit.reset()
        self.stuck.reset()

    def redirect(self, target_xy: tuple[float, float], path_xy: F64) -> None:
        """Go to a new target along ``path_xy`` (the team's assignment)."""
        self._deciding = self._replanning = None
        self.pursuit.reset()
        self.stuck.reset()
        self.target_xy = target_xy
        self.path_xy = path_xy
        self.mode = EXPLORING
