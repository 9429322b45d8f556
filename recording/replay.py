"""``mrslam replay``: publish a recording's messages onto the bus again, with their timing.

Messages go out in log-time order (ties in the order they were recorded), byte for byte as they
were recorded, each on its own key. The pause before a message is its log-time gap divided by
``speed``; ``speed`` 0 sends as fast as the link takes them. Gaps longer than ``max_gap_s`` of
recorded time are shortened to that (a recording that spans a pause or mixes clocks does not
stall). Publishers block rather than drop when the link is congested.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from recording.reader import RecordedMessage, read_recording
from schemas import keys
from schemas.bus import Bus
from schemas.config import BusConfig

log = logging.getLogger(__name__)

WIRE_PREFIX = f"{keys.ROOT}/"


@lru_cache(maxsize=256)
def _pattern(key_expr: str) -> re.Pattern[str]:
    chunks = key_expr.split("/")
    rx = ""
    for i, chunk in enumerate(chunks):
        first = i == 0 or (i == 1 and chunks[0] == "**")
        if chunk == "**":
            if i == 0:  # leading: any chunks, each with its slash, before the next one
                rx += "(?:[^/]+/)*" if len(chunks) > 1 else "[^/]+(?:/[^/]+)*"
            else:
                rx += "(?:/[^/]+)*"
            continue
        piece = "[^/]+" if chunk == "*" else re.escape(chunk)
        rx += piece if first else "/" + piece
    return re.compile(f"^{rx}$")


def key_matches(key_expr: str, key: str) -> bool:
    """Zenoh's wildcards: ``*`` is one chunk between slashes, ``**`` any number of chunks."""
    return _pattern(key_expr).match(key) is not None


def select(messages: Iterable[RecordedMessage], only: Sequence[str] = (),
           until_ns: int | None = None) -> list[RecordedMessage]:
    """The messages to replay, in log-time order: on keys matching any of ``only`` (all wire
    keys when empty: not the Foxglove channels beside them), logged at or before ``until_ns``."""
    return sorted((m for m in messages
                   if m.topic.startswith(WIRE_PREFIX)
                   and (not only or any(key_matches(k, m.topic) for k in only))
                   and (until_ns is None or m.log_time_ns <= until_ns)),
                  key=lambda m: m.log_time_ns)


def run(path: str | Path, bus: BusConfig | None = None, *, speed: float = 1.0,
        only: Sequence[str] = (), until_ns: int | None = None, max_gap_s: float = 5.0,
        linger_s: float = 0.5, stop: threading.Event | None = None) -> dict[str, Any]:
    """Replay the recording at ``path``; returns what was sent and what could not be read."""
    import zenoh

    if speed < 0:
        raise ValueError("speed must be >= 0 (0: as fast as possible)")
    rec = read_recording(path)
    todo = select(rec.messages, only, until_ns)
    stop = stop or threading.Event()
    b = bus or BusConfig()
    sent: Counter[str] = Counter()
    t0 = time.monotonic()
    with Bus.from_config(b) as session:
        publishers: dict[str, Any] = {}
        offset_s, prev_ns = 0.0, todo[0].log_time_ns if todo else 0
        for m in todo:
            offset_s += min(max(m.log_time_ns - prev_ns, 0) * 1e-9, max_gap_s)
            prev_ns = m.log_time_ns
            if speed > 0:
                wait = t0 + offset_s / speed - time.monotonic()
                if wait > 0 and stop.wait(wait):
                    break
            elif stop.is_set():
                break
            pub = publishers.get(m.topic)
            if pub is None:
                pub = publishers[m.topic] = session.session.declare_publisher(
                    m.topic, congestion_control=zenoh.CongestionControl.BLOCK)
            pub.put(m.data)
            sent[m.type_name or "unknown"] += 1
        time.sleep(linger_s)  # let the last messages leave before the session closes
        for pub in publishers.values():
            pub.undeclare()
    r = rec.report
    summary = {"path": str(path), "published": sum(sent.values()), "by_type": dict(sent),
               "selected": len(todo), "recorded": r.messages,
               "unreadable": r.unreadable_messages, "intact": r.intact,
               "span_s": (todo[-1].log_time_ns - todo[0].log_time_ns) * 1e-9 if todo else 0.0,
               "wall_s": time.monotonic() - t0}
    log.info("replayed %d of %d messages in %.1f s", summary["published"], r.messages,
             summary["wall_s"])
    return summary
