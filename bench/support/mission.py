"""A long mission in one process: the simulator and the server's core in lockstep, no bus.

The robots of a scenario explore with the server's own core (``ServerCore.on_scan``: SLAM,
teams, map matching, planning, control) as the server runs it; tag messages are left out
(rendering camera frames would cost more than the server), so teams form from the start poses
(``known_starts``) or on the maps alone. Once a robot has nothing left to do — its team is
done — it is sent on patrol: an operator's goto to a random free place of its team's map
(``ServerCore.operate``), again each time it gets there or gives up, so the robots keep
driving and scanning for as long as the mission lasts, as a surveillance robot would.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas import Scan
from schemas.messages import quantise_ranges_mm
from schemas.occupancy import FREE_BELOW
from server.command.operator import OperatorCommand
from server.config import ServerConfig
from server.core import ServerCore
from sim.config import DEFAULT_SCENARIOS, load_scenario
from sim.loader import load_world
from sim.simulator import Observation, SimParams, Simulator

PATROL_MODES = {"done", "idle", "waiting", "finished", "terminated"}
#: a patrol goal not reached in this long [sim s] is replaced by another
GOAL_TIMEOUT_S = 120.0


def scan_of(sim: Simulator, obs: Observation, rid: str) -> Scan:
    """Robot ``rid``'s scan of a simulated step, as its agent would send it."""
    lid = obs.beams[rid]
    return Scan(robot_id=rid, seq=obs.step + 1, stamp_ns=obs.stamp_ns,
                odom_pose=obs.odometry[rid][0], angle_min_rad=lid.angle_min_rad,
                angle_increment_rad=lid.angle_increment_rad,
                range_min_mm=round(lid.range_min_m * 1000),
                range_max_mm=round(lid.range_max_m * 1000),
                ranges_mm=quantise_ranges_mm(obs.ranges_m[rid], lid.range_min_m,
                                             lid.range_max_m))


@dataclass
class Mission:
    """One mission: ``step()`` advances the simulation by one step (0.1 s)."""

    sim: Simulator
    core: ServerCore
    rng: np.random.Generator
    patrol_after_s: float
    patrols: int = 0
    goals: dict[str, tuple[float, float]] = field(default_factory=dict)
    goal_ns: dict[str, int] = field(default_factory=dict)   # when each goal was sent
    steps: int = 0

    @property
    def sim_time_s(self) -> float:
        return self.steps * self.sim.p.step_ns / 1e9

    def step(self) -> None:
        obs = self.sim.sense()
        for rid in self.sim.robots:
            cmd = self.core.on_scan(scan_of(self.sim, obs, rid))
            self.sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
        self.sim.advance()
        self.steps += 1
        if self.steps % 50 == 0 and self.sim_time_s >= self.patrol_after_s:
            self._patrol(obs.stamp_ns)

    def _patrol(self, stamp_ns: int) -> None:
        """Send every robot without work to a random free place of its team's map."""
        states = self.core.robot_states(stamp_ns)
        for r in states.robots:
            goal = self.goals.get(r.robot_id)
            near = goal is not None and np.hypot(r.pose[0] - goal[0], r.pose[1] - goal[1]) < 1.0
            stale = stamp_ns - self.goal_ns.get(r.robot_id, stamp_ns) > GOAL_TIMEOUT_S * 1e9
            if goal is not None and not near and not stale and r.mode not in PATROL_MODES:
                continue
            if goal is None and r.mode not in PATROL_MODES:
                continue
            grid = self.core.planning_grid(r.team_id)
            d = grid.data
            free = np.flatnonzero((d >= 0) & (d < FREE_BELOW))
            if len(free) == 0:
                continue
            iy, ix = np.unravel_index(self.rng.choice(free), d.shape)
            xy = (grid.origin_xy[0] + (ix + 0.5) * grid.resolution_m,
                  grid.origin_xy[1] + (iy + 0.5) * grid.resolution_m)
            status, _ = self.core.operate(OperatorCommand("goto", r.robot_id, xy), stamp_ns)
            if status == 200:
                self.goals[r.robot_id] = xy
                self.goal_ns[r.robot_id] = stamp_ns
                self.patrols += 1


def scenario_mission(scenario: str, robots: int, seed: int = 0, known_starts: bool = True,
                     patrol_after_s: float = 0.0,
                     config: Callable[[dict[str, Any]], dict[str, Any]] | None = None
                     ) -> Mission:
    """The first ``robots`` robots of a packaged scenario, with the demo's settings."""
    case = load_scenario(DEFAULT_SCENARIOS, scenario)
    world = Path(DEFAULT_SCENARIOS).parent / str(case["world"])
    spawn = {rid: tuple(float(v) for v in p)
             for rid, p in list(dict(case["robots"]).items())[:robots]}
    cells = float(case.get("grid_cells_per_m", 15))
    data: dict[str, Any] = {
        "robots": sorted(spawn),
        "slam": {"grid": {"resolution_m": 1.0 / cells}},
        "explore": {"total_area_m2": float(case.get("total_area_m2", 500.0)),
                    "coverage_threshold": float(case.get("coverage_threshold", 0.95))},
        "control": {"v_mps": float(case.get("v_mps", 0.3)),
                    "omega_max_rps": float(case.get("omega_max_rps", 1.5))},
        "teams": {"start_poses": ({rid: list(p) for rid, p in spawn.items()}
                                  if known_starts else {})},
    }
    cfg = ServerConfig.model_validate(config(data) if config else data)
    sim = Simulator(load_world(world), spawn, SimParams(), seed=seed)  # type: ignore[arg-type]
    return Mission(sim, ServerCore(cfg), np.random.default_rng(seed), patrol_after_s)
