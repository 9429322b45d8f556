"""Foxglove's well-known message types, written as JSON beside the wire channels.

Foxglove Studio cannot read msgpack, but it draws channels whose schema is named after one of
its own types (``foxglove.LaserScan``, ``foxglove.Grid``, ``foxglove.FrameTransform``,
``foxglove.PoseInFrame``) and whose messages are JSON in that type's layout. These functions turn
decoded mrslam messages into such JSON objects. Frames: each team's map frame is named after the
team, each robot's body frame after the robot; the transforms come from the server's robot
states, so scans appear where the server placed the robot.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterator
from typing import Any

import numpy as np

from schemas import MapUpdate, RobotStates, Scan

TOPIC_PREFIX = "foxglove"
TF_TOPIC = f"{TOPIC_PREFIX}/tf"
INT8 = 2  # foxglove.PackedElementField numeric type

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"},
                                          "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}
_POSE = {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}}


def _schema(title: str, props: dict[str, Any]) -> bytes:
    return json.dumps({"title": title, "type": "object", "properties": props}).encode()


#: JSON Schemas of the Foxglove types we write, by schema name.
SCHEMAS: dict[str, bytes] = {
    "foxglove.LaserScan": _schema("foxglove.LaserScan", {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE,
        "start_angle": {"type": "number"}, "end_angle": {"type": "number"},
        "ranges": {"type": "array", "items": {"type": "number"}},
        "intensities": {"type": "array", "items": {"type": "number"}}}),
    "foxglove.Grid": _schema("foxglove.Grid", {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE,
        "column_count": {"type": "integer"},
        "cell_size": {"type": "object", "properties": {"x": {"type": "number"},
                                                       "y": {"type": "number"}}},
        "row_stride": {"type": "integer"}, "cell_stride": {"type": "integer"},
        "fields": {"type": "array", "items": {"type": "object", "properties": {
            "name": {"type": "string"}, "offset": {"type": "integer"},
            "type": {"type": "integer"}}}},
        "data": {"type": "string", "contentEncoding": "base64"}}),
    "foxglove.FrameTransform": _schema("foxglove.FrameTransform", {
        "timestamp": _TIME, "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"}, "translation": _VEC3, "rotation": _QUAT}),
    "foxglove.PoseInFrame": _schema("foxglove.PoseInFrame", {
        "timestamp": _TIME, "frame_id": {"type": "string"}, "pose": _POSE}),
}

#: One converted message: (topic, schema name, JSON bytes).
Converted = tuple[str, str, bytes]


def _time(stamp_ns: int) -> dict[str, int]:
    return {"sec": stamp_ns // 10**9, "nsec": stamp_ns % 10**9}


def _quat(theta_rad: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(theta_rad / 2), "w": math.cos(theta_rad / 2)}


def _pose(x_m: float, y_m: float, theta_rad: float) -> dict[str, Any]:
    return {"position": {"x": x_m, "y": y_m, "z": 0.0}, "orientation": _quat(theta_rad)}


def _dump(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":")).encode()


def laser_scan(scan: Scan) -> Converted:
    """A scan in its robot's frame; no-return beams become 0 (Foxglove draws nothing there)."""
    r = scan.ranges_m()
    ranges = np.where(np.isfinite(r), r, 0.0).round(3).tolist()
    n = scan.n_beams
    return (f"{TOPIC_PREFIX}/robot/{scan.robot_id}/scan", "foxglove.LaserScan", _dump({
        "timestamp": _time(scan.stamp_ns), "frame_id": scan.robot_id, "pose": _pose(0, 0, 0),
        "start_angle": scan.angle_min_rad,
        "end_angle": scan.angle_min_rad + scan.angle_increment_rad * (n - 1),
        "ranges": ranges, "intensities": []}))


def grid(update: MapUpdate) -> Converted:
    """A team's occupancy grid (-1 unknown, 0..100 %) as one int8 field, row 0 at the origin."""
    cells = update.grid()
    x, y, theta = update.origin
    return (f"{TOPIC_PREFIX}/map/{update.team_id}", "foxglove.Grid", _dump({
        "timestamp": _time(update.stamp_ns), "frame_id": update.team_id,
        "pose": _pose(x, y, theta), "column_count": update.width,
        "cell_size": {"x": update.resolution_m, "y": update.resolution_m},
        "row_stride": update.width, "cell_stride": 1,
        "fields": [{"name": "occupancy", "offset": 0, "type": INT8}],
        "data": base64.b64encode(cells.tobytes()).decode()}))


def robot_poses(states: RobotStates) -> Iterator[Converted]:
    """Per robot: the transform team frame -> robot frame, and the pose in the team frame."""
    for est in states.robots:
        x, y, theta = est.pose
        t = _time(states.stamp_ns)
        yield (TF_TOPIC, "foxglove.FrameTransform", _dump({
            "timestamp": t, "parent_frame_id": est.team_id, "child_frame_id": est.robot_id,
            "translation": {"x": x, "y": y, "z": 0.0}, "rotation": _quat(theta)}))
        yield (f"{TOPIC_PREFIX}/robot/{est.robot_id}/pose", "foxglove.PoseInFrame", _dump({
            "timestamp": t, "frame_id": est.team_id, "pose": _pose(x, y, theta)}))


def convert(type_name: str | None, payload: bytes) -> list[Converted]:
    """Foxglove messages for one wire payload (none for types Foxglove has no view of).

    Raises SchemaError when the payload does not decode.
    """
    from schemas import decode

    if type_name == "Scan":
        return [laser_scan(decode(payload, Scan))]
    if type_name == "MapUpdate":
        return [grid(decode(payload, MapUpdate))]
    if type_name == "RobotStates":
        return list(robot_poses(decode(payload, RobotStates)))
    return []
