"""A server split over several worker processes, coordinated over Zenoh itself.

Each worker is a whole ``mrslam server`` with ``cluster.worker: N`` in its configuration, on
this machine or another one reachable through Zenoh routers (docs/scale.md). Every worker
hears every robot; each robot is served by one of them, its *owner*, and a team lives whole
in one worker — its joint graph with it.

- **Workers** hold the liveliness token ``mrslam/server/cluster/worker/<N>``: a worker killed
  or cut off vanishes within Zenoh's lease, and its robots with it.
- **Ownership** is a liveliness token too, ``mrslam/server/cluster/owner/<robot>/<N>``; a
  robot's agent obeys the worker that holds it (``robot_agent.command_gate``). A robot
  without an owner is claimed by the live worker that ranks highest for it (rendezvous
  hashing: every worker computes the same choice from the same workers, and a worker joining
  or leaving moves only the robots it wins or held). The robots of a worker that vanished wait
  ``handover_timeout_s`` for it (restarted on its state, it takes them back with their maps)
  before another worker serves them afresh. Two workers that claim the same robot for
  longer than ``handover_timeout_s`` (their views of the live workers differed) leave it to
  the lower number. A worker stopping on purpose (SIGTERM) first hands its teams, maps and
  all, to the lowest-numbered worker that stays, which asks for them one by one.
- **Teams move.** When robots of two workers see each other's tags, the lower-numbered worker
  takes the other robot's whole team: it claims the robot in advance, holds its messages, and
  asks the owner through its queryable ``mrslam/cluster/give/<N>``. The owner takes the team
  out of its core (``server.runtime.handover``) and answers with it — a header naming the team's
  robots, then the parcel in chunks under the bus's message size — and keeps its tokens a
  moment longer, so that no third worker claims a robot in between. The asker puts the team
  into its core, then the messages it held that the owner had not processed.

The bookkeeping here runs on Zenoh's threads (under one lock) and on the node's worker; the
core is touched only on the worker (``server.runtime.node``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from schemas import TagDetections, keys
from schemas.bus import Bus
from server.config import ClusterConfig

log = logging.getLogger(__name__)

CHUNK_BYTES = 1_000_000      # below the bus's 1.5 MB message limit
RELEASE_GRACE_S = 2.0        # a giver keeps its tokens this long after giving the team away
#: how a give request's answer begins when the robot was claimed but not mapped yet: the
#: asking worker maps it from its first scans, as a robot just joined (nothing is lost)
LET_GO = "let go before it was mapped"


class Route(Enum):
    MINE = "mine"      # served here
    WAIT = "wait"      # asked for: held until the team arrives
    OTHER = "other"    # another worker's


@dataclass
class Handover:
    """A team the worker asked for: the robots it will bring (from the answer's header) and
    the parcel's bytes, or why there are none."""

    asked: str
    robots: list[str] = field(default_factory=list)
    parcel: bytes | None = None
    error: str = ""


def _rank(robot_id: str, worker: int) -> bytes:
    return hashlib.blake2b(f"{robot_id}/{worker}".encode(), digest_size=8).digest()


class Cluster:
    """This worker's view of the others and of who serves which robot."""

    def __init__(self, bus: Bus, cfg: ClusterConfig,
                 on_give: Callable[[Any, list[str]], None],
                 on_handover: Callable[[Handover], None]) -> None:
        """``on_give(query, robots)``: another worker asks for these robots' teams (answer
        with ``answer``); ``on_handover(h)``: a team asked for arrived, or will not."""
        assert cfg.worker is not None
        self.bus, self.index, self.timeout_s = bus, cfg.worker, cfg.handover_timeout_s
        self._on_give, self._on_handover = on_give, on_handover
        self._lock = threading.Lock()
        self.workers: set[int] = set()
        self.sessions: set[str] = set()           # the workers' Zenoh sessions
        self.owners: dict[str, set[int]] = {}
        self.mine: dict[str, Any] = {}            # robot -> its owner token
        self.pulling: dict[str, float] = {}       # robot -> when asked (monotonic)
        self.released: dict[str, float] = {}      # robot -> when its token goes
        self._contested: dict[str, float] = {}    # robot -> since when another claims it too
        #: robots whose worker vanished: (that worker, since when); they wait for it to come
        #: back for ``timeout_s`` before another worker serves them afresh
        self.orphans: dict[str, tuple[int, float]] = {}
        #: robots this worker served before it restarted (in the state it resumed)
        self.resumed: set[str] = set()
        self.counters: Counter[str] = Counter()
        self.leaving: set[int] = set()            # workers stopping on purpose
        self._leaving_token: Any = None

    def start(self) -> None:
        self.bus.watch_alive(keys.ALL_CLUSTER_WORKERS, self._on_worker)
        self.bus.watch_alive(keys.ALL_CLUSTER_WORKER_SESSIONS, self._on_worker_session)
        self.bus.watch_alive(keys.ALL_CLUSTER_OWNERS, self._on_owner)
        self.bus.watch_alive(keys.ALL_CLUSTER_LEAVING, self._on_leaving)
        self.bus.serve_queries(keys.cluster_give(self.index), self._on_query)
        self.bus.declare_alive(keys.cluster_worker(self.index))

    # -- who is there, who serves what (Zenoh threads) -------------------------------------
    def _on_worker(self, key: str, alive: bool) -> None:
        w = self._track(self.workers, keys.cluster_worker_of(key), alive)
        if w is not None:
            log.info("server worker %d %s", w, "is up" if alive else "went away")

    def _on_worker_session(self, key: str, alive: bool) -> None:
        parsed = keys.cluster_worker_session_of(key)
        if parsed is not None:
            with self._lock:
                (self.sessions.add if alive else self.sessions.discard)(parsed[1])

    def is_worker(self, session: str | None) -> bool:
        """Whether ``session`` is one of the server's workers (whose commands are theirs to
        give)."""
        with self._lock:
            return session in self.sessions

    def _on_leaving(self, key: str, alive: bool) -> None:
        self._track(self.leaving, keys.cluster_worker_of(key, "leaving"), alive)

    def _track(self, workers: set[int], w: int | None, alive: bool) -> int | None:
        """Add or remove worker ``w`` (None: a key that names no worker) in ``workers``."""
        if w is not None:
            with self._lock:
                (workers.add if alive else workers.discard)(w)
        return w

    def leave(self) -> bool:
        """This worker is stopping on purpose: the lowest-numbered other live worker takes
        its teams, with their maps (it asks for them one by one, ``tick``). False: there is
        no other worker to take them."""
        with self._lock:
            others = self.workers - {self.index} - self.leaving
        if not others:
            return False
        self._leaving_token = self.bus.declare_token(keys.cluster_leaving(self.index))
        return True

    def _on_owner(self, key: str, alive: bool) -> None:
        parsed = keys.cluster_owner_of(key)
        if parsed is None:
            return
        rid, w = parsed
        with self._lock:
            held = self.owners.setdefault(rid, set())
            if alive:
                held.add(w)
                self.orphans.pop(rid, None)
            else:
                held.discard(w)
                if not held:
                    del self.owners[rid]
                    if w != self.index:
                        self.orphans[rid] = (w, time.monotonic())

    def _winner(self, robot_id: str) -> int:
        """(holding the lock) The worker that takes a robot nobody serves: the highest
        ranked of the live workers that are not leaving."""
        live = (self.workers | {self.index}) - self.leaving or {self.index}
        return max(live, key=lambda w: _rank(robot_id, w))

    def owner_of(self, robot_id: str) -> int | None:
        """The worker serving ``robot_id`` (this one included), the lowest if several claim
        it, or None."""
        with self._lock:
            gone = robot_id in self.released
            if robot_id in self.mine and not gone:
                return self.index
            held = self.owners.get(robot_id, set()) - ({self.index} if gone else set())
            return min(held) if held else None

    def route(self, robot_id: str) -> Route:
        """Where a message of ``robot_id`` goes; a robot nobody serves is claimed here if this
        worker ranks highest for it."""
        with self._lock:
            if robot_id in self.pulling:
                return Route.WAIT
            if robot_id in self.released:
                return Route.OTHER
            if robot_id in self.mine:
                return Route.MINE
            if self.owners.get(robot_id):
                return Route.OTHER
            if robot_id not in self.resumed:
                gone = self.orphans.get(robot_id)
                if gone is not None and time.monotonic() - gone[1] < self.timeout_s:
                    return Route.OTHER        # its worker may be back in a moment
                if self._winner(robot_id) != self.index:
                    return Route.OTHER
            self._claim(robot_id)
            self.counters["claimed"] += 1
            return Route.MINE

    def _claim(self, robot_id: str) -> None:
        """(holding the lock)"""
        if robot_id not in self.mine:
            self.mine[robot_id] = self.bus.declare_token(keys.cluster_owner(robot_id,
                                                                            self.index))

    def tags_here(self, msg: TagDetections, observer: Route) -> bool:
        """Whether this worker takes a tag message (its observer's, or as the lower-numbered
        of two workers whose robots saw each other, asking for the other's team)."""
        here = observer is not Route.OTHER
        o_owner = self.index if here else self.owner_of(msg.robot_id)
        if o_owner is None:
            return here
        for det in msg.detections:
            seen = det.observed_robot_id
            if seen == msg.robot_id:
                continue
            s_owner = self.owner_of(seen)
            if s_owner is None or s_owner == o_owner or min(o_owner, s_owner) != self.index:
                continue
            other, owner = (msg.robot_id, o_owner) if s_owner == self.index else (seen, s_owner)
            self.pull(other, owner)
            here = True
        return here

    # -- asking for a team -----------------------------------------------------------------
    def pull(self, robot_id: str, owner: int) -> None:
        """Ask ``owner`` for ``robot_id``'s team (once at a time), claiming the robot now."""
        with self._lock:
            if robot_id in self.mine or robot_id in self.pulling:
                return
            self.pulling[robot_id] = time.monotonic()
            self._claim(robot_id)
            self.counters["asked"] += 1
        log.info("asking worker %d for the team of robot %s", owner, robot_id)
        request = json.dumps({"robots": [robot_id], "to": self.index}).encode()
        try:
            self.bus.ask(keys.cluster_give(owner), request,
                         lambda replies, errors: self._answered(robot_id, replies, errors),
                         self.timeout_s)
        except Exception as e:
            self._answered(robot_id, [], [f"{type(e).__name__}: {e}"])

    def _answered(self, robot_id: str, replies: list[bytes], errors: list[str]) -> None:
        h = Handover(robot_id)
        try:
            if not replies:
                raise ValueError("; ".join(errors) or "no answer")
            head = json.loads(replies[0])
            h.robots = [str(r) for r in head["robots"]]
            chunks = replies[1:]
            if len(chunks) != int(head["chunks"]):
                raise ValueError(f"{len(chunks)} of {head['chunks']} chunks arrived")
            h.parcel = b"".join(chunks)
        except Exception as e:
            h.error = f"{type(e).__name__}: {e}" if not isinstance(e, ValueError) else str(e)
            h.robots, h.parcel = [], None
        with self._lock:
            for rid in h.robots:       # the team's other robots: claimed and held from now
                self._claim(rid)
                self.pulling.setdefault(rid, time.monotonic())
        self._on_handover(h)

    def settled(self, h: Handover, adopted: list[str]) -> None:
        """The worker is done with ``h``: ``adopted`` robots are served here, the others asked
        for are served here afresh (their team did not come)."""
        with self._lock:
            for rid in {h.asked, *h.robots, *adopted}:
                self.pulling.pop(rid, None)
            for rid in adopted:
                self._claim(rid)
        self.counters["adopted" if adopted else "not_adopted"] += 1

    # -- giving a team ---------------------------------------------------------------------
    def _on_query(self, query: Any) -> None:
        try:
            req = json.loads(query.payload.to_bytes() if query.payload is not None else b"")
            robots = [str(r) for r in req["robots"]]
        except Exception as e:
            query.reply_err(f"a give request needs {{'robots': [...]}}: {e}".encode())
            query.drop()
            self.counters["bad_requests"] += 1
            return
        self._on_give(query, robots)

    def answer(self, query: Any, robots: list[str], parcel: bytes | None, why: str = "") -> None:
        """Answer a give request with a team's parcel (``robots`` its robots, whose tokens
        go after a grace period), or with ``why`` there is none."""
        try:
            if parcel is None:
                query.reply_err(why.encode())
                return
            chunks = [parcel[i:i + CHUNK_BYTES] for i in range(0, len(parcel), CHUNK_BYTES)]
            key = keys.cluster_give(self.index)
            query.reply(key, json.dumps({"robots": robots, "chunks": len(chunks)}).encode())
            for c in chunks:
                query.reply(key, c)
            with self._lock:
                for rid in robots:
                    self.released[rid] = time.monotonic() + RELEASE_GRACE_S
                self.resumed.difference_update(robots)
            self.counters["given"] += 1
        finally:
            query.drop()

    def let_go(self, robot_id: str) -> None:
        """Stop serving ``robot_id`` (claimed here, not yet mapped) for the worker that asks
        for it; its token goes after the same grace as a given team's."""
        with self._lock:
            if robot_id in self.mine:
                self.released[robot_id] = time.monotonic() + RELEASE_GRACE_S
            self.resumed.discard(robot_id)
        self.counters["let_go"] += 1

    def serves(self, robot_id: str) -> bool:
        with self._lock:
            return robot_id in self.mine and robot_id not in self.released

    # -- the worker's periodic check -------------------------------------------------------
    def tick(self) -> list[str]:
        """Tokens of given robots go once their grace is over; returns the robots this worker
        must drop: claimed by a lower-numbered worker too for longer than the timeout, or
        resumed from its state but served by another worker meanwhile."""
        now = time.monotonic()
        drop: list[str] = []
        with self._lock:
            for rid in list(self.resumed):
                if rid not in self.mine and self.owners.get(rid):
                    self.resumed.discard(rid)
                    drop.append(rid)
                    self.counters["resumed_but_taken"] += 1
            for rid, until in list(self.released.items()):
                if now >= until:
                    del self.released[rid]
                    token = self.mine.pop(rid, None)
                    if token is not None:
                        self.bus.undeclare(token)
            for rid in list(self.mine):
                lower = any(w < self.index for w in self.owners.get(rid, ()))
                if not lower or rid in self.pulling or rid in self.released:
                    self._contested.pop(rid, None)
                    continue
                since = self._contested.setdefault(rid, now)
                if now - since >= self.timeout_s:
                    del self._contested[rid]
                    self.bus.undeclare(self.mine.pop(rid))
                    drop.append(rid)
                    self.counters["conflicts_lost"] += 1
            take = self._from_leavers()
        if take is not None:
            self.pull(*take)
        return drop

    def _from_leavers(self) -> tuple[str, int] | None:
        """(holding the lock) The next robot to ask a leaving worker for, if this worker is
        the one that takes its teams (the lowest-numbered that stays): one at a time, so a
        team comes whole and once."""
        if not self.leaving or self.index in self.leaving:
            return None
        staying = (self.workers | {self.index}) - self.leaving
        if min(staying) != self.index:
            return None
        for rid, held in self.owners.items():
            if rid in self.pulling and held & self.leaving:
                return None          # a team from a leaver is on its way
        for rid, held in sorted(self.owners.items()):
            if held and held <= self.leaving and rid not in self.mine:
                self.counters["taken_from_leaving"] += 1
                return rid, min(held)
        return None

    def summary(self) -> dict[str, Any]:
        with self._lock:
            return {"worker": self.index, "workers_seen": sorted(self.workers),
                    "robots_served": sorted(set(self.mine) - set(self.released)),
                    **dict(self.counters)}
