"""A run as Foxglove draws it: wire messages turned into the Foxglove SDK's well-known types.

Channels (topic → type, all in ``foxglove.messages``; encoded as protobuf with the SDK's schemas):

- ``foxglove/robot/<id>/scan`` → ``LaserScan`` in the robot's frame; a beam without a return
  is +inf (REP 117's "no return"), which Foxglove draws nowhere, not a dot at the robot
- ``foxglove/map/<team>`` → ``Grid`` in the team's frame: the int8 occupancy (-1 unknown,
  0..100 %) and red/green/blue/alpha bytes of an occupancy palette, so it draws in map colours
- ``foxglove/tf`` → ``FrameTransforms``: the whole frame tree (``recording.frames``) with every
  scan, estimate and event, so the tree is complete at every scan's stamp and after a seek
- ``foxglove/robot/<id>/pose`` → ``PoseInFrame`` and ``…/trajectory`` → ``PosesInFrame``: the
  server's estimates, in the robot's team frame
- ``foxglove/events`` → ``Log``: every server event (merges, rejections, robots lost) as a log line

The conversion is pure (no I/O); ``recording.writer`` puts the result into MCAP and
``recording.live`` serves it over the SDK's WebSocket server.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from foxglove import Schema
from foxglove import messages as fm

from recording.frames import FrameTree, Transform
from schemas import Event, MapUpdate, RobotStates, Scan, decode
from schemas.occupancy import UNKNOWN

TOPIC_PREFIX = "foxglove"
TF_TOPIC = f"{TOPIC_PREFIX}/tf"
EVENTS_TOPIC = f"{TOPIC_PREFIX}/events"
MESSAGE_ENCODING = "protobuf"

#: one converted message: (topic, SDK message)
Converted = tuple[str, Any]

#: Grid cell layout: occupancy int8, then the palette's RGBA bytes
_GRID_FIELDS = [
    fm.PackedElementField(name="occupancy", offset=0, type=fm.PackedElementFieldNumericType.Int8),
    *[fm.PackedElementField(name=n, offset=1 + i, type=fm.PackedElementFieldNumericType.Uint8)
      for i, n in enumerate(("red", "green", "blue", "alpha"))],
]
_EVENT_LEVEL = {"merge": fm.LogLevel.Info, "robot_joined": fm.LogLevel.Info,
                "target_reached": fm.LogLevel.Info, "terminated": fm.LogLevel.Info,
                "merge_rejected": fm.LogLevel.Warning, "merge_undone": fm.LogLevel.Warning,
                "robot_lost": fm.LogLevel.Warning, "stuck": fm.LogLevel.Warning,
                "error": fm.LogLevel.Error}


def schema_of(msg: Any) -> Schema:
    """The SDK's schema of a message (name ``foxglove.<Type>``, protobuf descriptor set)."""
    schema: Schema = type(msg).get_schema()
    return schema


def _time(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=stamp_ns // 10**9, nsec=stamp_ns % 10**9)


def _quat(theta_rad: float) -> fm.Quaternion:
    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(theta_rad / 2), w=math.cos(theta_rad / 2))


def _pose(x_m: float, y_m: float, theta_rad: float) -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=x_m, y=y_m, z=0.0), orientation=_quat(theta_rad))


def laser_scan(scan: Scan) -> Converted:
    """A scan in its robot's frame; beams without a return become +inf."""
    n = scan.n_beams
    return (f"{TOPIC_PREFIX}/robot/{scan.robot_id}/scan", fm.LaserScan(
        timestamp=_time(scan.stamp_ns), frame_id=scan.robot_id, pose=_pose(0.0, 0.0, 0.0),
        start_angle=scan.angle_min_rad,
        end_angle=scan.angle_min_rad + scan.angle_increment_rad * (n - 1),
        ranges=scan.ranges_m().tolist()))


def occupancy_palette(cells: np.ndarray) -> np.ndarray:
    """RGBA bytes per cell: unknown faint grey, free white, occupied darker with its %."""
    c = cells.astype(np.int16)
    grey = (235 - c.clip(0, 100) * 235 // 100).astype(np.uint8)   # 0 % -> 235, 100 % -> 0
    rgba = np.stack([grey, grey, grey, np.full_like(grey, 255)], axis=-1)
    rgba[c == UNKNOWN] = (128, 128, 128, 60)
    return rgba


def grid(update: MapUpdate) -> Converted:
    """A team's occupancy grid with its palette, row 0 at the origin (as nav2 stores it)."""
    cells = update.grid()
    data = np.concatenate([cells.view(np.uint8)[..., None], occupancy_palette(cells)], axis=-1)
    x, y, theta = update.origin
    return (f"{TOPIC_PREFIX}/map/{update.team_id}", fm.Grid(
        timestamp=_time(update.stamp_ns), frame_id=update.team_id, pose=_pose(x, y, theta),
        column_count=update.width,
        cell_size=fm.Vector2(x=update.resolution_m, y=update.resolution_m),
        row_stride=update.width * 5, cell_stride=5, fields=_GRID_FIELDS,
        data=np.ascontiguousarray(data).tobytes()))


def frame_transforms(transforms: list[Transform]) -> Converted:
    return (TF_TOPIC, fm.FrameTransforms(transforms=[fm.FrameTransform(
        timestamp=_time(t.stamp_ns), parent_frame_id=t.parent, child_frame_id=t.child,
        translation=fm.Vector3(x=t.pose[0], y=t.pose[1], z=0.0),
        rotation=_quat(t.pose[2])) for t in transforms]))


def log_event(ev: Event) -> Converted:
    robots = f" [{', '.join(ev.robot_ids)}]" if ev.robot_ids else ""
    return (EVENTS_TOPIC, fm.Log(timestamp=_time(ev.stamp_ns),
                                 level=_EVENT_LEVEL.get(ev.kind, fm.LogLevel.Unknown),
                                 message=f"{ev.kind}: {ev.message}{robots}",
                                 name=f"server/{ev.team_id}" if ev.team_id else "server"))


class FoxgloveView:
    """Turns the run's wire messages, in order, into Foxglove messages; keeps the frame tree."""

    def __init__(self) -> None:
        self.frames = FrameTree()

    def convert(self, type_name: str | None, payload: bytes) -> list[Converted]:
        """Foxglove messages for one wire payload (none for types Foxglove has no view of).

        Raises SchemaError when the payload does not decode.
        """
        if type_name == "Scan":
            scan = decode(payload, Scan)
            return [frame_transforms(self.frames.add_scan(scan)), laser_scan(scan)]
        if type_name == "MapUpdate":
            return [grid(decode(payload, MapUpdate))]
        if type_name == "RobotStates":
            return self._states(decode(payload, RobotStates))
        if type_name == "Event":
            ev = decode(payload, Event)
            return [log_event(ev), frame_transforms(self.frames.add_event(ev))]
        return []

    def _states(self, states: RobotStates) -> list[Converted]:
        out = [frame_transforms(self.frames.add_states(states))]
        t = _time(states.stamp_ns)
        for est in states.robots:
            rid = est.robot_id
            out.append((f"{TOPIC_PREFIX}/robot/{rid}/pose", fm.PoseInFrame(
                timestamp=t, frame_id=est.team_id, pose=_pose(*est.pose))))
            traj = self.frames.trajectories.get(rid, [])
            out.append((f"{TOPIC_PREFIX}/robot/{rid}/trajectory", fm.PosesInFrame(
                timestamp=t, frame_id=self.frames.trajectory_frame.get(rid, est.team_id),
                poses=[_pose(float(p[0]), float(p[1]), float(p[2])) for p in traj])))
        return out
