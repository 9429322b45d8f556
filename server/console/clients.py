"""The open pages: one bounded queue each, so a slow or hung browser costs only itself.

Frames are encoded once (server-sent events: ``event: <kind>`` and one ``data:`` line of
JSON) and handed to every page's queue. A page that does not keep up loses old frames, never
blocks the others: a newer frame of the same slot (a team's map, the robot states, the health
table) replaces the one still waiting, and unslotted frames (events) are kept up to a bound,
the oldest dropped first.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict, deque
from typing import Any

from server.console.model import Frame

#: unslotted frames (events) a page may have waiting before the oldest go
MAX_WAITING = 256


def encode(frame: Frame) -> bytes:
    """A frame as one server-sent event."""
    data = json.dumps(frame.data, separators=(",", ":"), allow_nan=False)
    return f"event: {frame.kind}\ndata: {data}\n\n".encode()


class PageQueue:
    """Frames waiting for one page (the console's thread puts, the page's thread takes)."""

    def __init__(self) -> None:
        self._slots: OrderedDict[str, bytes] = OrderedDict()
        self._rest: deque[bytes] = deque(maxlen=MAX_WAITING)
        self._cv = threading.Condition()
        self.dropped = 0
        self.closed = False

    def put(self, slot: str | None, data: bytes) -> None:
        with self._cv:
            if slot is None:
                if len(self._rest) == self._rest.maxlen:
                    self.dropped += 1
                self._rest.append(data)
            else:
                if slot in self._slots:
                    self.dropped += 1
                    del self._slots[slot]
                self._slots[slot] = data
            self._cv.notify()

    def take(self, timeout_s: float) -> list[bytes]:
        """Everything waiting (events first, in order), or [] after ``timeout_s``."""
        with self._cv:
            if not self._slots and not self._rest and not self.closed:
                self._cv.wait(timeout_s)
            out = list(self._rest) + list(self._slots.values())
            self._rest.clear()
            self._slots.clear()
            return out

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class Pages:
    """The open pages' queues (any thread)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._queues: set[PageQueue] = set()
        self._lock = threading.Lock()
        self.dropped_by_closed = 0

    def open(self) -> PageQueue | None:
        """A queue for a new page, or None when ``limit`` pages are open."""
        with self._lock:
            if len(self._queues) >= self.limit:
                return None
            q = PageQueue()
            self._queues.add(q)
            return q

    def close(self, q: PageQueue) -> None:
        with self._lock:
            self._queues.discard(q)
            self.dropped_by_closed += q.dropped
        q.close()

    def send(self, frame: Frame) -> None:
        data = encode(frame)
        with self._lock:
            queues = list(self._queues)
        for q in queues:
            q.put(frame.slot, data)

    def close_all(self) -> None:
        with self._lock:
            queues, self._queues = list(self._queues), set()
        for q in queues:
            q.close()

    def counters(self) -> dict[str, Any]:
        with self._lock:
            return {"pages": len(self._queues),
                    "frames_dropped": self.dropped_by_closed + sum(q.dropped
                                                                   for q in self._queues)}
