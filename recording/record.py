"""``mrslam record``: a bus client that writes every message under ``mrslam/**`` to MCAP, with
Foxglove's channels beside them (``recording.foxglove``); with ``foxglove_port`` it also serves
those channels live over the Foxglove SDK's WebSocket server (``recording.live``).

It stops on SIGINT/SIGTERM (or when ``stop`` is set, or after ``duration_s``) and always finishes
the file, so a recorder killed by its process group leaves an indexed, readable recording.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from recording.writer import Compression, McapRecorder
from schemas import keys
from schemas.bus import Bus
from schemas.config import BusConfig
from schemas.types import SCHEMA_VERSION

log = logging.getLogger(__name__)


def run(out: str | Path, bus: BusConfig | None = None, *, foxglove: bool = True,
        foxglove_port: int | None = None, foxglove_host: str = "127.0.0.1",
        compression: Compression = "zstd", flush_period_s: float = 1.0,
        duration_s: float | None = None, key: str = keys.ALL,
        exclude: Sequence[str] = (), stop: threading.Event | None = None) -> dict[str, Any]:
    """Record until stopped; returns the recorder's counters (also stored in the file).
    Keys matching any of the ``exclude`` key expressions are left out (and counted).
    ``foxglove``: write the Foxglove channels into the file; ``foxglove_port``: serve them live
    on that port (0: any free one) of ``foxglove_host``."""
    b = bus or BusConfig()
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    import zenoh

    skip = [zenoh.KeyExpr(e) for e in exclude]
    excluded = [0]
    meta = {"schema_version": str(SCHEMA_VERSION), "key": key, "exclude": ",".join(exclude),
            "started_unix_ns": str(time.time_ns())}
    t0 = time.monotonic()
    live = None
    if foxglove_port is not None:
        from recording.live import FoxgloveLive

        live = FoxgloveLive(foxglove_port, foxglove_host)
    with Bus.from_config(b) as session, \
            McapRecorder(out, compression, foxglove, metadata=meta, live=live) as rec:
        # the file appears only once the session is up (the demo waits for it)
        def add(k: str, payload: bytes) -> None:
            if skip and any(e.intersects(zenoh.KeyExpr(k)) for e in skip):
                excluded[0] += 1
                return
            rec.add(k, payload)

        session.subscribe_raw(key, add)
        log.info("recording %s into %s", key, out)
        deadline = None if duration_s is None else t0 + duration_s
        while not stop.wait(flush_period_s):
            rec.flush()
            if deadline is not None and time.monotonic() >= deadline:
                break
        session.close()  # no callback runs past this point; then the file is finished
    if live is not None:
        live.close()
    summary = {"out": str(out), "wall_s": time.monotonic() - t0, "excluded": excluded[0],
               **rec.stats.as_dict()}
    log.info("recorded %d messages on %d keys", summary["messages"], summary["keys"])
    return summary
