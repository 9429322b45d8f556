"""A mission on a known map in one process: the simulator and the server's core in lockstep.

Robots start where the caller says (random free places, say) in a world whose map the core
was given; nothing tells the server where they are. ``KnownMission.step`` advances by one
simulation step; the mission records when each robot was placed in the map and how far from
the truth it was then (its pose in the map's frame against the simulator's, brought into
that frame by ``T_world_map``, where the map's frame lies in the world).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt

from bench.support.mission import scan_of
from schemas.occupancy import FREE
from schemas.se2 import compose, inverse, wrap_angle
from server.config import ServerConfig
from server.core import ServerCore
from server.knownmap.ghosts import MAP_TEAM
from server.knownmap.mapdata import KnownMap
from sim.config import DEFAULT_SCENARIOS, load_scenario
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from sim.world_map import world_map

F64 = NDArray[np.float64]
WORLDS = Path(DEFAULT_SCENARIOS).parent


def free_poses(world: Path, n: int, rng: np.random.Generator, clearance_m: float = 0.5,
               apart_m: float = 1.0, exclude: list[tuple[float, float]] = ()) -> list[F64]:
    """``n`` random poses (any heading) in the world's free space, at least ``clearance_m``
    from walls, ``apart_m`` from each other and from ``exclude``."""
    grid, _ = world_map(world, 0.05)
    free = grid.cells == FREE
    clear = distance_transform_edt(free) * grid.resolution_m >= clearance_m
    rows, cols = np.nonzero(clear)
    out: list[F64] = []
    taken = list(exclude)
    for _ in range(1000 * n):
        if len(out) == n:
            break
        k = int(rng.integers(len(rows)))
        x = grid.origin[0] + (cols[k] + 0.5) * grid.resolution_m
        y = grid.origin[1] + (rows[k] + 0.5) * grid.resolution_m
        if all(math.hypot(x - a, y - b) >= apart_m for a, b in taken):
            out.append(np.array([x, y, rng.uniform(-math.pi, math.pi)]))
            taken.append((x, y))
    if len(out) < n:
        raise ValueError(f"{world.name}: no room for {n} places {apart_m} m apart")
    return out


def pose_away(world: Path, at: F64, distance_m: float, rng: np.random.Generator,
              tolerance_m: float = 0.5) -> F64:
    """A random free pose (any heading) ``distance_m`` ± ``tolerance_m`` from ``at``."""
    for _ in range(100):
        q = free_poses(world, 1, rng)[0]
        if abs(math.hypot(*(q[:2] - at[:2])) - distance_m) <= tolerance_m:
            return q
    raise ValueError(f"{world.name}: no free place {distance_m} m from {at[:2]}")


def demo_config(scenario: str = "small-house-3", **known: Any) -> ServerConfig:
    """The demo's server settings for a scenario, on a known map (``known``: its keys)."""
    case = load_scenario(DEFAULT_SCENARIOS, scenario)
    cells = float(case.get("grid_cells_per_m", 15))
    return ServerConfig.model_validate({
        "slam": {"grid": {"resolution_m": 1.0 / cells, "p_hit": 0.75, "p_miss": 0.35}},
        "explore": {"lam": 0.5, "total_area_m2": float(case.get("total_area_m2", 400.0)),
                    "coverage_threshold": float(case.get("coverage_threshold", 0.95))},
        "control": {"v_mps": float(case.get("v_mps", 0.3)),
                    "omega_max_rps": float(case.get("omega_max_rps", 1.5)),
                    "lookahead_m": float(case.get("lookahead_m", 1.0))},
        "known_map": known})


@dataclass
class Placed:
    robot_id: str
    after_s: float          # since it started searching
    at_s: float             # simulated time when it was placed
    error_m: float          # its pose in the map's frame against the truth, when placed
    error_deg: float


@dataclass
class KnownMission:
    sim: Simulator
    core: ServerCore
    T_world_map: F64
    steps: int = 0
    searching_since: dict[str, float] = field(default_factory=dict)
    placed: list[Placed] = field(default_factory=list)
    wrong_m: float = 0.5            # a placement farther than this from the truth is wrong

    @property
    def sim_time_s(self) -> float:
        return self.steps * self.sim.p.step_ns / 1e9

    def step(self) -> None:
        obs = self.sim.sense()
        for rid in self.sim.robots:
            before = self._placed(rid)
            self.searching_since.setdefault(rid, self.sim_time_s)
            cmd = self.core.on_scan(scan_of(self.sim, obs, rid))
            self.sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
            if not before and self._placed(rid):
                err = self.error(rid)
                self.placed.append(Placed(rid, self.sim_time_s - self.searching_since[rid],
                                          self.sim_time_s, *err))
            elif before and not self._placed(rid):       # lost: it searches again
                self.searching_since[rid] = self.sim_time_s
        self.sim.advance()
        self.steps += 1

    def _placed(self, rid: str) -> bool:
        r = self.core.robots.get(rid)
        return r is not None and r.team_id == MAP_TEAM

    def error(self, rid: str) -> tuple[float, float]:
        """The robot's pose in the map against the truth: metres and degrees."""
        truth = compose(inverse(self.T_world_map), np.array(self.sim.robots[rid].pose))
        est = self.core.robots[rid].pose
        return (float(math.hypot(*(est[:2] - truth[:2]))),
                float(abs(math.degrees(wrap_angle(est[2] - truth[2])))))

    def wrong(self) -> list[Placed]:
        return [p for p in self.placed if p.error_m > self.wrong_m]

    def run_until(self, t_s: float, done: Any = None) -> None:
        while self.sim_time_s < t_s and not (done is not None and done(self)):
            self.step()


def mission(world: Path, known: KnownMap, spawn: dict[str, F64], cfg: ServerConfig,
            T_world_map: F64, seed: int = 0) -> KnownMission:
    sim = Simulator(load_world(world), {r: tuple(p) for r, p in spawn.items()},  # type: ignore[misc]
                    SimParams(), seed=seed)
    return KnownMission(sim, ServerCore(cfg, known=known), np.asarray(T_world_map, float))
