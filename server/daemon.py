"""``mrslam server``: the central daemon. Opens the Zenoh router, runs the node until it is
interrupted (SIGINT/SIGTERM) or, with ``exit_when_done``, until every team has finished, then
writes its outputs."""

from __future__ import annotations

import logging
import signal
import threading
import time
from pathlib import Path
from typing import Any

from schemas.bus import Bus
from server.config import ServerConfig

log = logging.getLogger(__name__)


def run(config_path: str | Path | None = None, overrides: dict[str, Any] | None = None,
        stop: threading.Event | None = None) -> dict[str, Any]:
    """Run the server until ``stop`` is set, a signal arrives, or (``exit_when_done``) the
    exploration has finished. Returns the summary."""
    from schemas.config_loading import load_config, write_resolved
    from server.node import ServerNode
    from server.outputs import write_outputs

    cfg = load_config(ServerConfig, config_path, overrides)
    out = Path(cfg.out) if cfg.out else None
    if out is not None:
        write_resolved(cfg, out, "server_config.yaml")
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    b = cfg.bus
    with Bus.from_config(b) as bus:
        node = ServerNode(bus, cfg)
        node.start()
        log.info("server up (%s on %s)", b.mode, ", ".join(b.listen or b.connect))
        t0 = time.monotonic()
        while not stop.wait(0.2):
            if cfg.exit_when_done and node.core.finished:
                time.sleep(0.5)  # let the last commands and events go out
                if node.core.finished:  # not when a merge was undone meanwhile
                    break
        node.stop()
        summary = {"wall_s": time.monotonic() - t0, **node.summary()}
        if out is not None:
            write_outputs(node.core, out, summary)
    return summary
