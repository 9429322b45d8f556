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
#: the chunk between a liveliness token's key and its holder's session id in the companion
#: token ``Bus.declare_alive`` declares beside it
HOLDER_CHUNK = "zid"

# wildcards for subscribers
ALL = f"{ROOT}/**"
ALL_SCANS = f"{ROOT}/robot/*/scan"
ALL_TAGS = f"{ROOT}/robot/*/tags"
ALL_STATUS = f"{ROOT}/robot/*/status"
ALL_ALIVE = f"{ROOT}/robot/*/alive"
ALL_CMD_VEL = f"{ROOT}/robot/*/cmd_vel"


# the workers of a server split over several processes (server.runtime.cluster); who works
# and who serves which robot are under the server's keys, where robots may read them (their
# agent obeys the worker that serves it), asking for a team and leaving are not
def cluster_worker(index: int) -> str:
    """Liveliness token of worker ``index`` (declared with its session's companion)."""
    return f"{ROOT}/server/cluster/worker/{int(index)}"


def cluster_owner(robot_id: str, index: int) -> str:
    """Liveliness token: worker ``index`` serves robot ``robot_id``."""
    return f"{ROOT}/server/cluster/owner/{_rid(robot_id)}/{int(index)}"


def cluster_owners(robot_id: str) -> str:
    """The owner tokens of robot ``robot_id``, whichever worker holds them."""
    return f"{ROOT}/server/cluster/owner/{_rid(robot_id)}/*"


def cluster_leaving(index: int) -> str:
    """Liveliness token: worker ``index`` is stopping and hands its teams on."""
    return f"{ROOT}/cluster/leaving/{int(index)}"


def cluster_give(index: int) -> str:
    """Worker ``index``'s queryable that hands a team over to the worker asking."""
    return f"{ROOT}/cluster/give/{int(index)}"


ALL_CLUSTER_WORKERS = f"{ROOT}/server/cluster/worker/*"
#: the session companions of the workers' tokens (``Bus.declare_alive``)
ALL_CLUSTER_WORKER_SESSIONS = f"{ROOT}/server/cluster/worker/*/{HOLDER_CHUNK}/*"
ALL_CLUSTER_OWNERS = f"{ROOT}/server/cluster/owner/*/*"
ALL_CLUSTER_LEAVING = f"{ROOT}/cluster/leaving/*"
_CLUSTER_PREFIX = {"worker": [ROOT, "server", "cluster", "worker"],
                   "owner": [ROOT, "server", "cluster", "owner"],
                   "leaving": [ROOT, "cluster", "leaving"]}


def cluster_owner_of(key: str) -> tuple[str, int] | None:
    """(robot, worker) of an owner token's key, or None."""
    parts = key.split("/")
    if len(parts) != 6 or parts[:4] != _CLUSTER_PREFIX["owner"] or not _ID.match(parts[4]) \
            or not parts[5].isdigit():
        return None
    return parts[4], int(parts[5])


def cluster_worker_of(key: str, kind: str = "worker") -> int | None:
    """The worker number of a worker token's key (``kind`` ``worker``) or of a leaving one
    (``leaving``), or None."""
    prefix = _CLUSTER_PREFIX[kind]
    parts = key.split("/")
    if len(parts) != len(prefix) + 1 or parts[:-1] != prefix or not parts[-1].isdigit():
        return None
    return int(parts[-1])


def cluster_worker_session_of(key: str) -> tuple[int, str] | None:
    """(worker, session id) of a worker token's session companion, or None."""
    parts = key.split("/")
    prefix = _CLUSTER_PREFIX["worker"]
    if len(parts) != len(prefix) + 3 or parts[:len(prefix)] != prefix \
            or not parts[len(prefix)].isdigit() or parts[len(prefix) + 1] != HOLDER_CHUNK \
            or not parts[-1]:
        return None
    return int(parts[len(prefix)]), parts[-1]


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
