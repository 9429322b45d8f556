"""Zenoh key expressions, built only here.

Robots publish only under ``mrslam/robot/<id>/``; the server publishes under ``mrslam/server/``;
the simulator and the agents' sim backends talk under ``mrslam/sim/``.
"""

from __future__ import annotations

import re

from schemas.types import ID_PATTERN

ROOT = "mrslam"
_ID = re.compile(ID_PATTERN)


def _rid(robot_id: str) -> str:
    if not _ID.match(robot_id):
        raise ValueError(f"robot id {robot_id!r} does not match {ID_PATTERN}")
    return robot_id


# agent -> server
def robot_scan(robot_id: str) -> str:
    return f"{ROOT}/robot/{_rid(robot_id)}/scan"


def robot_tags(robot_id: str) -> str:
    return f"{ROOT}/robot/{_rid(robot_id)}/tags"


def robot_status(robot_id: str) -> str:
    return f"{ROOT}/robot/{_rid(robot_id)}/status"


def robot_alive(robot_id: str) -> str:
    """Liveliness token of a running agent."""
    return f"{ROOT}/robot/{_rid(robot_id)}/alive"


# server -> agent
def robot_cmd_vel(robot_id: str) -> str:
    return f"{ROOT}/robot/{_rid(robot_id)}/cmd_vel"


# server -> anyone
SERVER_MAP = f"{ROOT}/server/map"
SERVER_ROBOTS = f"{ROOT}/server/robots"
SERVER_EVENTS = f"{ROOT}/server/events"
SERVER_ALIVE = f"{ROOT}/server/alive"

# wildcards for subscribers
ALL = f"{ROOT}/**"
ALL_SCANS = f"{ROOT}/robot/*/scan"
ALL_TAGS = f"{ROOT}/robot/*/tags"
ALL_STATUS = f"{ROOT}/robot/*/status"
ALL_ALIVE = f"{ROOT}/robot/*/alive"
ALL_CMD_VEL = f"{ROOT}/robot/*/cmd_vel"


# the workers of a server split over several processes (server.runtime.cluster)
def cluster_worker(index: int) -> str:
    """Liveliness token of worker ``index``."""
    return f"{ROOT}/cluster/worker/{int(index)}"


def cluster_owner(robot_id: str, index: int) -> str:
    """Liveliness token: worker ``index`` serves robot ``robot_id``."""
    return f"{ROOT}/cluster/owner/{_rid(robot_id)}/{int(index)}"


def cluster_leaving(index: int) -> str:
    """Liveliness token: worker ``index`` is stopping and hands its teams on."""
    return f"{ROOT}/cluster/leaving/{int(index)}"


def cluster_give(index: int) -> str:
    """Worker ``index``'s queryable that hands a team over to the worker asking."""
    return f"{ROOT}/cluster/give/{int(index)}"


ALL_CLUSTER_WORKERS = f"{ROOT}/cluster/worker/*"
ALL_CLUSTER_OWNERS = f"{ROOT}/cluster/owner/*/*"
ALL_CLUSTER_LEAVING = f"{ROOT}/cluster/leaving/*"


def cluster_owner_of(key: str) -> tuple[str, int] | None:
    """(robot, worker) of an owner token's key, or None."""
    parts = key.split("/")
    if len(parts) != 5 or parts[:3] != [ROOT, "cluster", "owner"] or not _ID.match(parts[3]) \
            or not parts[4].isdigit():
        return None
    return parts[3], int(parts[4])


def cluster_worker_of(key: str, kind: str = "worker") -> int | None:
    """The worker number of a ``mrslam/cluster/<kind>/<N>`` token's key (``worker`` or
    ``leaving``), or None."""
    parts = key.split("/")
    if len(parts) != 4 or parts[:3] != [ROOT, "cluster", kind] or not parts[3].isdigit():
        return None
    return int(parts[3])


# simulator <-> sim backend
SIM_CLOCK = f"{ROOT}/sim/clock"
SIM_TRUTH = f"{ROOT}/sim/truth"
SIM_ALIVE = f"{ROOT}/sim/alive"


def sim_lidar(robot_id: str) -> str:
    return f"{ROOT}/sim/robot/{_rid(robot_id)}/lidar"


def sim_odom(robot_id: str) -> str:
    return f"{ROOT}/sim/robot/{_rid(robot_id)}/odom"


def sim_image(robot_id: str) -> str:
    return f"{ROOT}/sim/robot/{_rid(robot_id)}/image"


def sim_motor(robot_id: str) -> str:
    return f"{ROOT}/sim/robot/{_rid(robot_id)}/motor"


def sim_ack(robot_id: str) -> str:
    return f"{ROOT}/sim/robot/{_rid(robot_id)}/ack"


SIM_ALL_MOTOR = f"{ROOT}/sim/robot/*/motor"
SIM_ALL_ACK = f"{ROOT}/sim/robot/*/ack"

_ROBOT_KEY = re.compile(rf"^{ROOT}/(?:sim/)?robot/([^/]+)/")


def robot_id_of(key: str) -> str | None:
    """The robot id inside a ``mrslam/robot/<id>/...`` or ``mrslam/sim/robot/<id>/...`` key."""
    m = _ROBOT_KEY.match(key)
    return m.group(1) if m else None


#: Message type published on each key; ``<id>`` stands for a robot id.
KEY_TEMPLATES: dict[str, str] = {
    "Scan": f"{ROOT}/robot/<id>/scan",
    "TagDetections": f"{ROOT}/robot/<id>/tags",
    "RobotStatus": f"{ROOT}/robot/<id>/status",
    "VelocityCommand": f"{ROOT}/robot/<id>/cmd_vel",
    "MapUpdate": SERVER_MAP,
    "RobotStates": SERVER_ROBOTS,
    "Event": SERVER_EVENTS,
    "SimClock": SIM_CLOCK,
    "SimGroundTruth": SIM_TRUTH,
    "SimLidar": f"{ROOT}/sim/robot/<id>/lidar",
    "SimOdometry": f"{ROOT}/sim/robot/<id>/odom",
    "SimImage": f"{ROOT}/sim/robot/<id>/image",
    "SimMotorCommand": f"{ROOT}/sim/robot/<id>/motor",
    "SimStepAck": f"{ROOT}/sim/robot/<id>/ack",
}
_KEY_TYPES = [(re.compile("^" + t.replace("<id>", "[^/]+") + "$"), name)
              for name, t in KEY_TEMPLATES.items()]


def message_type_name(key: str) -> str | None:
    """Name of the message type published on ``key`` (used by recorders and tools)."""
    for pattern, name in _KEY_TYPES:
        if pattern.match(key):
            return name
    return None
