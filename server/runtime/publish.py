"""What the server tells everyone (``mrslam/server/**``), from its worker thread: events as the
core raises them, the robots' states every ``states_period_s``, and each team's map when it
changed (the latest per team also answers queries, for a client that joins late)."""

from __future__ import annotations

import time
from typing import Any

from schemas import keys
from schemas.bus import Bus
from server.core import ServerCore


class Publisher:
    def __init__(self, bus: Bus, states_period_s: float) -> None:
        self.bus = bus
        self.states_period_s = states_period_s
        self.latest_maps: list[Any] = []     # each live team's latest map
        self._next_states = 0.0
        self._map_stamp = 0

    def serve(self) -> None:
        """Answer queries for the maps with each team's latest."""
        self.bus.serve(keys.SERVER_MAP, lambda: list(self.latest_maps))

    def tick(self, core: ServerCore, now_ns: int) -> None:
        for ev in core.pop_events():
            self.bus.publish(keys.SERVER_EVENTS, ev, block=True)
        now = time.monotonic()
        if now >= self._next_states:
            self._next_states = now + self.states_period_s
            self.bus.publish(keys.SERVER_ROBOTS, core.robot_states(now_ns))
        if core.map_stamp_ns != self._map_stamp:
            self._map_stamp = core.map_stamp_ns
            fresh = core.map_updates(core.progress.changed_teams())
            for m in fresh:
                self.bus.publish(keys.SERVER_MAP, m)
            latest = {m.team_id: m for m in self.latest_maps if m.team_id in core.teams}
            latest.update((m.team_id, m) for m in fresh)
            self.latest_maps = list(latest.values())
