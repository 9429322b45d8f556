"""The server daemon's configuration (``mrslam server -c server.yaml``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.config import DEFAULT_PORT, BusConfig
from server.slam.config import GridConfig, SlamConfig


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ExploreConfig(_Model):
    explorer: Literal["voronoi", "frontier"] = "voronoi"
    lam: float = Field(1.0, ge=0.0, le=1.0, description="C = λ·d_robot + (1−λ)·d_origin")
    total_area_m2: float | None = Field(
        None, gt=0.0, description="area to cover; unknown: stop when no frontier is reachable")
    coverage_threshold: float = Field(0.98, gt=0.0, le=1.0)
    replan_period_s: float = Field(4.0, gt=0.0, description="re-decide the target this often")
    visited_radius_m: float = Field(1.0, gt=0.0, description="targets this close count as visited")
    unknown_as_obstacle: bool = Field(True, description="plan only through observed free space")


class ControlConfig(_Model):
    v_mps: float = Field(0.3, gt=0.0)
    omega_max_rps: float = Field(1.5, gt=0.0)
    lookahead_m: float = Field(1.0, gt=0.0)
    goal_tolerance_m: float = Field(0.3, gt=0.0)
    robot_radius_m: float = Field(0.13, gt=0.0)
    command_ttl_s: float = Field(0.5, gt=0.0, le=10.0)
    vfh: bool = True
    stuck_window_s: float = Field(8.0, gt=0.0)
    stuck_min_progress_m: float = Field(0.15, gt=0.0)


def _router() -> BusConfig:
    return BusConfig(mode="router", listen=[f"tcp/0.0.0.0:{DEFAULT_PORT}"], connect=[])


class ServerConfig(_Model):
    bus: BusConfig = Field(default_factory=_router)
    robots: list[str] | None = Field(
        None, description="robots allowed to join; None accepts any robot that appears")
    # one observation decides a cell for exploration: a beam through it makes it free
    # (p 0.35 < 0.4), an endpoint in it makes it occupied (p 0.75 > 0.7)
    slam: SlamConfig = SlamConfig(grid=GridConfig(p_hit=0.75, p_miss=0.35))
    explore: ExploreConfig = ExploreConfig()
    control: ControlConfig = ControlConfig()
    map_period_s: float = Field(
        1.0, gt=0.0, description="map updates and coverage checks, every this much scan time")
    states_period_s: float = Field(0.25, gt=0.0)
    queue_per_robot: int = Field(50, ge=1, description="scans waiting beyond this are dropped")
    out: str | None = Field(None, description="folder for maps, trajectories and the summary")
    exit_when_done: bool = Field(False, description="stop once every team has finished")
