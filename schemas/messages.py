"""Every message on the mrslam bus, defined once.

Messages are msgspec structs encoded as msgpack maps. Numeric arrays travel as raw little-endian
bytes (``bytes`` fields, msgpack ``bin``); their element type is part of the field's name and
description. Each message carries ``schema_version``, ``seq`` and ``stamp_ns``, and ``robot_id``
when it is about one robot. Cross-field rules (array lengths, ordering of limits) are checked in
``__post_init__``, which msgspec runs on decode as well as on construction.
"""

from __future__ import annotations

import zlib
from typing import Annotated, Literal

import msgspec
import numpy as np

from schemas.occupancy import OCCUPIED, UNKNOWN
from schemas.types import (
    MAX_RANGE_MM,
    NO_RETURN_MM,
    SCHEMA_VERSION,
    Finite,
    Fraction,
    Metres,
    Pose2,
    PositiveMetres,
    Radians,
    RobotId,
    Seq,
    Sigma,
    StampNs,
    TeamId,
    Version,
)

MAX_BEAMS = 8192
RangeMm = Annotated[int, msgspec.Meta(ge=0, le=MAX_RANGE_MM, description="[mm]")]
MAX_GRID_CELLS = 4096 * 4096


def fail(field: str, reason: str) -> None:
    """Raise the error ``__post_init__`` uses; the codec turns it into a SchemaError."""
    raise ValueError(f"{field}: {reason}")


class Message(msgspec.Struct, kw_only=True):
    schema_version: Version = SCHEMA_VERSION
    seq: Seq = 0
    stamp_ns: StampNs = 0

    def __post_init__(self) -> None:
        if self.schema_version != SCHEMA_VERSION:
            fail("schema_version", f"unsupported version {self.schema_version}, expected "
                 f"{SCHEMA_VERSION}")


def _check_beams(ranges_mm: bytes, angle_increment_rad: float, range_min_mm: int,
                 range_max_mm: int) -> None:
    if len(ranges_mm) % 2:
        fail("ranges_mm", f"odd byte length {len(ranges_mm)} for uint16 ranges")
    n = len(ranges_mm) // 2
    if not 1 <= n <= MAX_BEAMS:
        fail("ranges_mm", f"{n} beams, expected 1..{MAX_BEAMS}")
    if angle_increment_rad == 0.0 or abs(angle_increment_rad) * n > 2 * np.pi + 1e-6:
        fail("angle_increment_rad", f"{angle_increment_rad} does not fit {n} beams in 360 deg")
    if not range_min_mm < range_max_mm:
        fail("range_max_mm", f"range_max_mm {range_max_mm} <= range_min_mm {range_min_mm}")


def quantise_ranges_mm(ranges_m: np.ndarray, range_min_m: float = 0.0,
                       range_max_m: float = MAX_RANGE_MM / 1000.0) -> bytes:
    """Ranges [m] -> uint16 millimetres; non-finite or out-of-limit readings become no-return."""
    r = np.asarray(ranges_m, dtype=np.float64)
    valid = np.isfinite(r) & (r >= range_min_m) & (r <= range_max_m)
    mm = np.where(valid, np.rint(np.where(valid, r, 0.0) * 1000.0), NO_RETURN_MM)
    mm = np.clip(mm, NO_RETURN_MM, MAX_RANGE_MM)
    mm[valid & (mm == NO_RETURN_MM)] = 1
    return mm.astype("<u2").tobytes()


def ranges_from_mm(ranges_mm: bytes) -> np.ndarray:
    """uint16 millimetres -> float64 metres, ``inf`` for no-return."""
    mm = np.frombuffer(ranges_mm, dtype="<u2")
    out = mm.astype(np.float64) / 1000.0
    out[mm == NO_RETURN_MM] = np.inf
    return out


class LidarSweep(Message, kw_only=True):
    """One 2D LIDAR sweep: beam ``i`` points at ``angle_min_rad + i * angle_increment_rad``."""

    robot_id: RobotId
    angle_min_rad: Radians
    angle_increment_rad: Radians
    range_min_mm: RangeMm
    range_max_mm: RangeMm
    ranges_mm: Annotated[bytes, msgspec.Meta(
        description="uint16 little-endian ranges [mm], 0 = no return")]

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_beams(self.ranges_mm, self.angle_increment_rad, self.range_min_mm, self.range_max_mm)

    @property
    def range_min_m(self) -> float:
        return self.range_min_mm / 1000.0

    @property
    def range_max_m(self) -> float:
        return self.range_max_mm / 1000.0

    @property
    def n_beams(self) -> int:
        return len(self.ranges_mm) // 2

    def ranges_m(self) -> np.ndarray:
        return ranges_from_mm(self.ranges_mm)

    def angles_rad(self) -> np.ndarray:
        return self.angle_min_rad + self.angle_increment_rad * np.arange(self.n_beams)


class Scan(LidarSweep, kw_only=True):
    """A LIDAR sweep plus the wheel-odometry pose at the time of the sweep (agent -> server)."""

    odom_pose: Pose2


class TagDetection(msgspec.Struct, kw_only=True):
    """One fiducial on another robot, in the observer's base frame."""

    tag_id: Annotated[int, msgspec.Meta(ge=0, le=4095)]
    observed_robot_id: RobotId
    range_m: PositiveMetres
    bearing_rad: Radians
    yaw_rad: Annotated[float, msgspec.Meta(
        ge=-7.0, le=7.0, description="observed robot's heading relative to the observer [rad]")]
    sigma_range_m: Sigma
    sigma_bearing_rad: Sigma
    sigma_yaw_rad: Sigma
    reprojection_error_px: Annotated[float, msgspec.Meta(ge=0.0, le=1e4)] = 0.0
    located_by: Annotated[Literal["tag", "lidar"], msgspec.Meta(
        description="where range and bearing come from: the tag's pose, or the LIDAR returns "
                    "off the observed robot's body (the tag then names the robot)")] = "tag"


class TagDetections(Message, kw_only=True):
    robot_id: RobotId
    detections: Annotated[list[TagDetection], msgspec.Meta(max_length=64)]


RobotState = Literal["starting", "ok", "degraded", "error", "stopped"]


class RobotStatus(Message, kw_only=True):
    robot_id: RobotId
    state: RobotState
    message: Annotated[str, msgspec.Meta(max_length=512)] = ""
    battery_v: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] | None = None
    cpu_percent: Annotated[float, msgspec.Meta(ge=0.0, le=10000.0)] = 0.0
    rss_mb: Annotated[float, msgspec.Meta(ge=0.0, le=1e6)] = 0.0
    scans_sent: Seq = 0
    commands_received: Seq = 0
    errors: Seq = 0


class VelocityCommand(Message, kw_only=True):
    """Body velocity for one robot, valid for ``ttl_s`` after ``stamp_ns``; then stop."""

    robot_id: RobotId
    v_mps: Annotated[float, msgspec.Meta(ge=-5.0, le=5.0)]
    omega_rps: Annotated[float, msgspec.Meta(ge=-20.0, le=20.0)]
    ttl_s: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.5


class MapUpdate(Message, kw_only=True):
    """A team's occupancy grid: zlib-compressed int8 cells, row-major from ``origin``.

    Cell values follow nav2's OccupancyGrid: -1 unknown, 0..100 occupancy probability [%].
    """

    team_id: TeamId
    robot_ids: Annotated[list[RobotId], msgspec.Meta(max_length=256)]
    width: Annotated[int, msgspec.Meta(ge=1, le=65535)]
    height: Annotated[int, msgspec.Meta(ge=1, le=65535)]
    resolution_m: Annotated[float, msgspec.Meta(gt=0.0, le=100.0)]
    origin: Pose2
    encoding: Literal["zlib-int8"] = "zlib-int8"
    cells: Annotated[bytes, msgspec.Meta(description="zlib(int8 cells, row-major)")]

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.width * self.height > MAX_GRID_CELLS:
            fail("width", f"{self.width}x{self.height} grid exceeds {MAX_GRID_CELLS} cells")
        self.grid()  # a map whose cells do not decode is not a map

    @classmethod
    def from_grid(cls, grid: np.ndarray, **fields: object) -> MapUpdate:
        """Build from a (height, width) int8 grid (-1 unknown, 0..100 occupied %)."""
        g = np.ascontiguousarray(grid, dtype=np.int8)
        cells = zlib.compress(g.tobytes(), 1)
        return cls(width=g.shape[1], height=g.shape[0], cells=cells, **fields)  # type: ignore[arg-type]

    def grid(self) -> np.ndarray:
        """Decompressed (height, width) int8 grid; raises ValueError when inconsistent."""
        n = self.width * self.height
        d = zlib.decompressobj()
        try:
            raw = d.decompress(self.cells, n + 1)
        except zlib.error as e:
            fail("cells", f"not zlib data ({e})")
        if len(raw) != n or d.unconsumed_tail:
            fail("cells", f"holds {len(raw)}+ cells, expected {n}")
        grid = np.frombuffer(raw, dtype=np.int8).reshape(self.height, self.width)
        if grid.min() < UNKNOWN or grid.max() > OCCUPIED:
            fail("cells", f"values outside {UNKNOWN}..{OCCUPIED}")
        return grid


RobotMode = Literal["waiting", "exploring", "returning", "stuck", "done", "lost", "idle"]
#: where a robot stands on a known map: "" without one (``server.knownmap``)
Localisation = Literal["", "searching", "placed", "lost"]


class Hypothesis(msgspec.Struct, kw_only=True):
    """One place a searching robot may be on the known map: its pose in the map's frame,
    and how strongly its own map fits there (summed match scores: larger fits better)."""

    pose: Pose2
    strength: Finite


class RobotEstimate(msgspec.Struct, kw_only=True):
    robot_id: RobotId
    team_id: TeamId
    pose: Pose2
    pose_sigma: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)
    mode: RobotMode = "waiting"
    target: tuple[Metres, Metres] | None = None
    distance_m: PositiveMetres = 0.0
    keyframes: Seq = 0
    last_scan_stamp_ns: StampNs = 0
    #: on a known map: searching, placed or lost (searching again); "" without a known map
    localisation: Localisation = ""
    #: while it searches: its strongest placements on the known map, strongest first
    hypotheses: Annotated[list[Hypothesis], msgspec.Meta(max_length=3)] = (
        msgspec.field(default_factory=list))


class TeamCoverage(msgspec.Struct, kw_only=True):
    team_id: TeamId
    robot_ids: list[RobotId]
    coverage: Fraction
    explored_m2: PositiveMetres


class RobotStates(Message, kw_only=True):
    """Every robot's pose in its team's frame, and each team's coverage."""

    robots: Annotated[list[RobotEstimate], msgspec.Meta(max_length=256)]
    teams: Annotated[list[TeamCoverage], msgspec.Meta(max_length=256)] = (
        msgspec.field(default_factory=list))


EventKind = Literal[
    "robot_joined", "robot_lost", "merge", "merge_rejected", "merge_undone", "target_reached",
    "stuck", "terminated", "error", "meeting", "operator", "detour", "map_changed",
]


class Event(Message, kw_only=True):
    kind: EventKind
    robot_ids: Annotated[list[RobotId], msgspec.Meta(max_length=256)] = (
        msgspec.field(default_factory=list))
    team_id: TeamId | None = None
    message: Annotated[str, msgspec.Meta(max_length=2048)] = ""
    transform: Pose2 | None = None
    covariance: Annotated[list[Finite], msgspec.Meta(min_length=9, max_length=9)] | None = None
    #: an event's figures by name (a detour's estimates: ``server.fleet.detours``)
    figures: Annotated[dict[Annotated[str, msgspec.Meta(max_length=64)], Finite],
                       msgspec.Meta(max_length=32)] | None = None
