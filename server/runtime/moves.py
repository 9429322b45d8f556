"""A team moving between the server's workers (``server.runtime.cluster``), as the worker
thread of one of them does it: which admitted messages are this worker's, giving a team to
another worker, adopting one from it, letting a team go that another serves, and handing every
team on before stopping. Each takes the node it works for."""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from server.runtime import handover
from server.runtime.cluster import LET_GO, Route
from server.runtime.work import AdoptWork, GiveWork

if TYPE_CHECKING:
    from server.runtime.node import ServerNode

log = logging.getLogger(__name__)


def routed(node: ServerNode, rid: str, ready: list[tuple[str, int, Any]]
            ) -> list[tuple[str, int, Any]]:
    """Of the admitted messages, those this worker serves; a robot whose team is on its
    way here has its scans held until it arrives, and another worker's robot its last
    ``queue_per_robot`` scans (the caller holds ``_cv``)."""
    assert node.cluster is not None
    route = node.cluster.route(rid)
    out = []
    for item in ready:
        if item[0] == "tags":
            if node.cluster.tags_here(item[2], route):
                out.append(item)
        elif route is Route.MINE:
            out.append(item)
            if node._recent:
                node._recent.pop(rid, None)
        elif route is Route.WAIT:
            node._held.setdefault(rid, []).append(item)
        else:
            # another worker's: kept a while, as the scans its owner may still have waiting
            # when its team is asked for here (given away unprocessed, they come from here)
            recent = node._recent.get(rid)
            if recent is None:
                recent = node._recent[rid] = deque(maxlen=node.cfg.queue_per_robot)
            recent.append(item)
    return out


def give(node: ServerNode, item: GiveWork) -> None:
    """Another worker asks for a team: the first of ``robots`` served here leaves with its
    whole team (journaled as given); a team that cannot be packed stays."""
    assert node.cluster is not None
    query, robots = item.query, item.robots
    for rid in robots:
        if not node.cluster.serves(rid):
            continue
        if rid not in node.core.robots:
            # claimed here, its first scans still waiting: the asker serves it from them
            node.cluster.let_go(rid)
            node.cluster.answer(query, [], None, f"{LET_GO}: worker {node.cluster.index} "
                                f"had claimed {rid}, its first scans still waiting")
            return
        parcel = handover.release(node.core, rid)
        assert parcel is not None
        team = parcel.robot_ids
        parcel.extra = {r: node._own_stamps.get(r, 0) for r in team}
        try:
            data = handover.pack(parcel)
        except Exception as e:
            handover.adopt(node.core, parcel)
            node.cluster.answer(query, [], None, f"team of {rid} could not be packed: {e}")
            raise
        try:
            node.cluster.answer(query, team, data)
        except Exception:
            handover.adopt(node.core, parcel)   # it did not leave: it stays here
            raise
        # (journaled once it has left: a crash before this line resumes the team here
        # too, and the copy the other worker took wins; see Cluster.tick)
        if node.journal is not None:
            node.journal.gave(team, node.clock.now_ns())
        for r in team:
            node._own_stamps.pop(r, None)
        log.info("team of %s (%s) given to another worker (%d kB)", rid, ", ".join(team),
                 len(data) // 1024)
        return
    node.cluster.answer(query, [], None,
                        f"worker {node.cluster.index} does not serve {', '.join(robots)}")


def adopt(node: ServerNode, item: AdoptWork) -> None:
    """A team asked for arrived (into the core, journaled whole), or did not (its robots
    are served here afresh); then the robots' held scans that the giver had not taken."""
    h = item.handover
    assert node.cluster is not None
    adopted: list[str] = []
    if h.parcel is not None:
        try:
            parcel = handover.unpack(h.parcel)
            handover.adopt(node.core, parcel)
        except handover.ParcelError as e:
            node.errors += 1
            log.error("the team of %s arrived unreadable (%s): served afresh", h.asked, e)
        else:
            adopted = parcel.robot_ids
            node._own_stamps.update(parcel.extra)
            if node.journal is not None:
                node.journal.adopted(h.parcel, node.clock.now_ns())
    elif LET_GO in h.error:     # the usual start: two workers claimed it at once
        log.info("%s: mapped here from its first scans (%s)", h.asked, h.error)
    else:
        log.warning("the team of %s did not come (%s): served afresh", h.asked, h.error)
    with node._cv:
        node.cluster.settled(h, adopted)
        for rid in {h.asked, *h.robots}:
            last = node._own_stamps.get(rid, -1)
            waiting = [*node._recent.pop(rid, ()), *node._held.pop(rid, [])]
            node._enqueue(rid, [it for it in waiting if it[2].stamp_ns > last])


def drop(node: ServerNode, rid: str) -> None:
    """Another worker serves ``rid`` (too): it keeps it, this one lets the robot's team
    go."""
    parcel = handover.release(node.core, rid)
    if parcel is not None and node.journal is not None:
        node.journal.gave(parcel.robot_ids, node.clock.now_ns())
    log.warning("robot %s left to the other worker that serves it", rid)


def leave(node: ServerNode, timeout_s: float) -> list[str]:
    """A worker stopping on purpose hands its teams on (``Cluster.leave``): waits until
    it serves no robot, or ``timeout_s``; returns the robots it still served."""
    if node.cluster is None or not node.cluster.leave():
        return []
    deadline = time.monotonic() + timeout_s
    while True:
        left = node.cluster.summary()["robots_served"]
        if not left or time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    log.info("worker %d handed its teams on%s", node.cluster.index,
             f"; still served here: {', '.join(left)}" if left else "")
    return list(left)
