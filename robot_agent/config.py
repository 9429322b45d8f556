"""The agent's configuration (``mrslam agent -c agent.yaml``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from schemas.config import BusConfig
from schemas.tags import CameraMount, TagLayout
from schemas.types import ID_PATTERN


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DetectorConfig(_Model):
    enabled: bool = True
    max_reprojection_px: float = Field(2.0, gt=0.0)
    range_a_m: float = Field(0.01, gt=0.0, description="σ_range = a + b r²")
    range_b_per_m: float = Field(0.01, ge=0.0)
    bearing_a_rad: float = Field(0.005, gt=0.0, description="σ_bearing = a + b r")
    bearing_b_rad_per_m: float = Field(0.002, ge=0.0)
    yaw_a_rad: float = Field(0.03, gt=0.0, description="σ_yaw = a + b r²")
    yaw_b_rad_per_m2: float = Field(0.03, ge=0.0)
    ambiguous_ratio: float = Field(3.0, ge=1.0)
    ambiguous_sigma_yaw_rad: float = Field(1.5, gt=0.0)


class LockstepConfig(_Model):
    """How the agent answers a lockstep simulator."""

    wait_for_command: bool = Field(
        True, description="while the server is alive, ack a step only after its command")
    command_timeout_s: float = Field(5.0, gt=0.0, description="wall-clock wait for it")


class AgentConfig(_Model):
    robot_id: str = Field("r1", pattern=ID_PATTERN)
    bus: BusConfig = BusConfig()
    backend: Literal["sim"] = "sim"
    status_period_s: float = Field(1.0, gt=0.0)
    v_max_mps: float = Field(0.5, gt=0.0, le=5.0, description="commands are clipped to this")
    omega_max_rps: float = Field(2.0, gt=0.0, le=20.0)
    stop_on_server_loss: bool = True
    max_queued_frames: int = Field(4, ge=1, description="older frames are dropped beyond this")
    tags: TagLayout = TagLayout()
    camera_mount: CameraMount = CameraMount()
    detector: DetectorConfig = DetectorConfig()
    lockstep: LockstepConfig = LockstepConfig()
