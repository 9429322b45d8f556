"""Which velocity commands may drive the robot.

On a network secured as ``deploy/`` describes, the router lets only the server publish on a
robot's ``cmd_vel``, and a stranger's command never arrives. Without access rules anyone who
reaches the router can publish there, so the agent checks what it can on its own:

1. the command is for this robot (``robot_id``);
2. a server is known: the agent binds to the first session it sees holding the server's
   liveliness token (``Bus.watch_holders``) and keeps it while that token lives. A server
   split over several workers (``server.runtime.cluster``) has every worker hold that token;
   there the agent binds to the worker whose owner token names this robot (the
   lowest-numbered if two do, as the workers settle it), and follows the robot's team when it
   moves to another worker. A worker's session is the first that holds its token and the
   server's, as for a single server;
3. the command's source (``Sample.source_info``, set by ``Bus.publish``) is that session;
4. its stamp is on the robot's clock, where the server puts it (the stamp of the scan it
   answers): not ahead of the robot's clock, not older than ``max_age_s``, not older than the
   last command obeyed.

Zenoh does not authenticate a sample's source: a sender who copies the source of one of the
server's messages passes check 3. Only TLS and access rules stop a determined stranger; these
checks stop anyone who merely publishes on the key.
"""

from __future__ import annotations

from typing import Literal

from schemas import VelocityCommand

Reason = Literal["other_robot", "no_server", "not_from_server", "from_future", "stale",
                 "out_of_order"]


class CommandGate:
    """Decides, command by command, whether the agent obeys; keeps what that needs."""

    def __init__(self, robot_id: str, max_age_s: float = 10.0, max_ahead_s: float = 1.0) -> None:
        self.robot_id = robot_id
        self.max_age_ns = round(max_age_s * 1e9)
        self.max_ahead_ns = round(max_ahead_s * 1e9)
        self.holders: list[str] = []      # sessions holding the server's token, first first
        #: a split server's workers' sessions by number, first first (as ``holders``)
        self.workers: dict[int, list[str]] = {}
        self.owned_by: set[int] = set()    # the workers that hold this robot's owner token
        self.last_stamp_ns: int | None = None
        self._last_now_ns: int | None = None

    @property
    def server(self) -> str | None:
        """The session the agent is bound to (None: no server)."""
        for w in sorted(self.owned_by):
            for zid in self.workers.get(w, ()):
                if zid in self.holders:     # a worker holds the server's token too
                    return zid
        return self.holders[0] if self.holders else None

    def _bound(self, before: str | None) -> str | None:
        if self.server != before:
            self.last_stamp_ns = None   # a new server, a new sequence of commands
        return self.server

    def server_holder(self, zid: str, alive: bool) -> str | None:
        """A session took or dropped the server's token; returns the server bound after it."""
        before = self.server
        if alive and zid not in self.holders:
            self.holders.append(zid)
        elif not alive and zid in self.holders:
            self.holders.remove(zid)
        return self._bound(before)

    def worker_session(self, worker: int, zid: str, alive: bool) -> str | None:
        """Worker ``worker`` of a split server is session ``zid`` (or went away); returns the
        server bound after it."""
        before = self.server
        sessions = self.workers.setdefault(worker, [])
        if alive and zid not in sessions:
            sessions.append(zid)
        elif not alive and zid in sessions:
            sessions.remove(zid)
        if not sessions:
            del self.workers[worker]
        return self._bound(before)

    def owner(self, worker: int, alive: bool) -> str | None:
        """Worker ``worker`` took or dropped this robot's owner token; returns the server
        bound after it."""
        before = self.server
        (self.owned_by.add if alive else self.owned_by.discard)(worker)
        return self._bound(before)

    def check(self, cmd: VelocityCommand, source: str | None, now_ns: int) -> Reason | None:
        """None when ``cmd`` (from session ``source``, at robot time ``now_ns``) may drive the
        robot, else why not."""
        if self._last_now_ns is not None and now_ns < self._last_now_ns:
            self.last_stamp_ns = None   # the robot's clock went back (a simulator restarted)
        self._last_now_ns = now_ns
        if cmd.robot_id != self.robot_id:
            return "other_robot"
        if self.server is None:
            return "no_server"
        if source != self.server:
            return "not_from_server"
        if cmd.stamp_ns > now_ns + self.max_ahead_ns:
            return "from_future"
        if cmd.stamp_ns < now_ns - self.max_age_ns:
            return "stale"
        if self.last_stamp_ns is not None and cmd.stamp_ns < self.last_stamp_ns:
            return "out_of_order"
        self.last_stamp_ns = cmd.stamp_ns
        return None
