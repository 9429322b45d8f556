"""The server's event log: what happened to robots and teams, in order, for the bus and the
run's outputs; and the sequence number every message the server publishes carries."""

from __future__ import annotations

from typing import Any

from schemas import Event


class EventLog:
    """Events since the last ``pop`` (for the bus) and all of them (for the outputs)."""

    def __init__(self) -> None:
        self.pending: list[Event] = []
        self.all: list[Event] = []
        self._seq = 0

    def next_seq(self) -> int:
        """The next sequence number of the server's messages (events, maps, states)."""
        self._seq += 1
        return self._seq

    def emit(self, kind: str, robot_ids: list[str], team_id: str | None, message: str,
             stamp_ns: int, **fields: Any) -> Event:
        """Log an event; ``fields`` are further ``Event`` fields (a merge's transform)."""
        ev = Event(kind=kind, robot_ids=robot_ids, team_id=team_id,  # type: ignore[arg-type]
                   message=message, seq=self.next_seq(), stamp_ns=max(stamp_ns, 0), **fields)
        self.pending.append(ev)
        self.all.append(ev)
        return ev

    def pop(self) -> list[Event]:
        """The events since the last call."""
        out, self.pending = self.pending, []
        return out
