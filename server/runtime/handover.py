"""A team leaving one server core for another, whole: the unit a split server moves.

When the server runs as several workers (``server.runtime.cluster``), each robot is served by one of
them, and a team's joint graph must live in one place. When robots of teams on two workers
meet, one worker gives the other its team: ``release`` takes the team out of its core — the
robots (SLAM, graph, navigator, lookout), the team (its grid mapper, links, visited targets,
coverage history), the teams merged into it (so a merge can still be undone), their merge
records, the team's last grid, the sightings and merge evidence waiting on its robots — and
``adopt`` puts all of it into the other core, where the team goes on as if it had always been
there. ``pack`` and ``unpack`` make the bytes that travel (with the code version: a parcel is
read only by the code that wrote it, as a snapshot is).

No I/O here; ``server.runtime.cluster`` moves the bytes, ``server.runtime.node`` calls these on
its worker.
"""

from __future__ import annotations

import io
import logging
import pickle
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from server.fleet.model import MergeRecord, RobotContext, Team
from server.planning import OccupancyGrid as PlanningGrid

if TYPE_CHECKING:
    from server.core import ServerCore

log = logging.getLogger(__name__)

MAGIC = b"mrslam-team\n"


class ParcelError(ValueError):
    """Bytes that are not a team parcel this code can read."""


@dataclass
class TeamParcel:
    """Everything of one team that a core holds, out of it."""

    team: Team
    robots: dict[str, RobotContext]
    retired: dict[str, Team] = field(default_factory=dict)
    merges: list[MergeRecord] = field(default_factory=list)
    grid: PlanningGrid | None = None
    next_update_ns: int | None = None
    sightings: list[tuple[int, str, Any]] = field(default_factory=list)
    evidence: dict[tuple[str, str], Any] = field(default_factory=dict)
    contradictions: dict[tuple[str, str], Any] = field(default_factory=dict)
    returning: dict[str, int] = field(default_factory=dict)
    #: the worker's own record per robot (e.g. the robot's own stamp of its last scan)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def robot_ids(self) -> list[str]:
        return list(self.team.robot_ids)


def _retired_into(core: ServerCore, team_id: str) -> dict[str, Team]:
    """The retired teams whose merges lead, one or more steps on, into ``team_id``."""
    out: dict[str, Team] = {}
    grew = True
    while grew:
        grew = False
        for tid, t in core.fleet.retired_teams.items():
            if tid not in out and (t.merged_into == team_id or t.merged_into in out):
                out[tid] = t
                grew = True
    return out


def release(core: ServerCore, robot_id: str) -> TeamParcel | None:
    """Take ``robot_id``'s whole team out of ``core`` (None: the robot is not there)."""
    fleet = core.fleet
    r = fleet.robots.get(robot_id)
    if r is None:
        return None
    team = fleet.teams.pop(r.team_id)
    ids = set(team.robot_ids)
    retired = _retired_into(core, team.team_id)
    for tid in retired:
        del fleet.retired_teams[tid]
    team_ids = {team.team_id, *retired}
    robots = {rid: fleet.robots.pop(rid) for rid in team.robot_ids}
    for rc in robots.values():
        # a team's coordination calls back into this fleet: the robot leaves with its own
        rc.nav.use_explorer(rc.nav.own_explorer)
    merges = [m for m in fleet.merges if m.team_id in team_ids]
    fleet.merges = [m for m in fleet.merges if m.team_id not in team_ids]
    desk, verifier = core.desk, core.merger.verifier
    sightings = [p for p in desk.pending if p[1] in ids]
    desk.pending = [p for p in desk.pending if p[1] not in ids]
    evidence = {k: verifier.pairs.pop(k) for k in list(verifier.pairs)
                if k[0] in team_ids or k[1] in team_ids}
    contradictions = {k: desk.contradictions.pop(k) for k in list(desk.contradictions)
                      if k[0] in ids or k[1] in ids}
    parcel = TeamParcel(
        team=team, robots=robots, retired=retired, merges=merges,
        grid=fleet.latest_grids.pop(team.team_id, None),
        next_update_ns=core.progress.next_update_ns.pop(team.team_id, None),
        sightings=sightings, evidence=evidence, contradictions=contradictions,
        returning={rid: core.returning.pop(rid) for rid in ids if rid in core.returning})
    log.info("team %s (%s) released", team.team_id, ", ".join(sorted(ids)))
    return parcel


def adopt(core: ServerCore, parcel: TeamParcel) -> None:
    """Put a released team into ``core``. A robot of the parcel that ``core`` still holds
    (left behind by an earlier worker's failure, say) is replaced by the parcel's."""
    fleet = core.fleet
    for rid in parcel.robots:
        if rid in fleet.robots:
            log.warning("robot %s was here already: the team arriving replaces it", rid)
            stale = release(core, rid)
            assert stale is not None
    fleet.robots.update(parcel.robots)
    fleet.teams[parcel.team.team_id] = parcel.team
    fleet.retired_teams.update(parcel.retired)
    fleet.merges.extend(parcel.merges)
    fleet.merges.sort(key=lambda m: m.stamp_ns)
    if parcel.grid is not None:
        fleet.latest_grids[parcel.team.team_id] = parcel.grid
    if parcel.next_update_ns is not None:
        core.progress.next_update_ns[parcel.team.team_id] = parcel.next_update_ns
    core.desk.pending.extend(parcel.sightings)
    core.desk.pending.sort(key=lambda p: p[0])
    core.merger.verifier.pairs.update(parcel.evidence)
    core.desk.contradictions.update(parcel.contradictions)
    core.returning.update(parcel.returning)
    fleet.coordinate(parcel.team)
    ids = ", ".join(sorted(parcel.robots))
    core.events.emit("robot_joined", sorted(parcel.robots), parcel.team.team_id,
                     f"team {parcel.team.team_id} ({ids}) moved here from another server "
                     f"worker", max(r.last_stamp_ns for r in parcel.robots.values()))
    log.info("team %s (%s) adopted", parcel.team.team_id, ids)


def pack(parcel: TeamParcel) -> bytes:
    """The parcel as bytes, headed by the code version that can read it."""
    from server.runtime.snapshot import VERSION

    buf = io.BytesIO()
    pickle.dump(parcel, buf, protocol=pickle.HIGHEST_PROTOCOL)
    return MAGIC + VERSION.encode() + b"\n" + zlib.compress(buf.getvalue(), 1)


def unpack(data: bytes) -> TeamParcel:
    """Raises ``ParcelError`` for anything but a parcel written by this very code."""
    from server.runtime.snapshot import VERSION

    if not data.startswith(MAGIC):
        raise ParcelError("not a team parcel")
    head, sep, body = data[len(MAGIC):].partition(b"\n")
    if not sep:
        raise ParcelError("team parcel without its version line")
    if head.decode(errors="replace") != VERSION:
        raise ParcelError(f"team parcel written by mrslam {head.decode(errors='replace')}, "
                          f"this is {VERSION}")
    try:
        parcel = pickle.loads(zlib.decompress(body))
    except Exception as e:
        raise ParcelError(f"team parcel unreadable: {type(e).__name__}: {e}") from None
    if not isinstance(parcel, TeamParcel):
        raise ParcelError(f"team parcel holds a {type(parcel).__name__}")
    return parcel
