"""The server's one bus module: Zenoh in, ``ServerCore`` in a worker thread, Zenoh out.

Zenoh delivers scans on its own threads; they are admitted (robot, key, stamp order), queued
per robot, and handed to the core by a single worker thread, so the core needs no locks. The
worker also publishes maps, robot states and events on their periods.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any

from schemas import Scan, TagDetections, keys
from schemas.bus import Bus
from server.config import ServerConfig
from server.core import ServerCore
from server.registry import Refused, RobotRegistry

log = logging.getLogger(__name__)


class ServerNode:
    def __init__(self, bus: Bus, cfg: ServerConfig, core: ServerCore | None = None) -> None:
        self.bus = bus
        self.cfg = cfg
        self.core = core or ServerCore(cfg)
        self.registry = RobotRegistry(cfg.robots)
        self.dropped: dict[str, int] = {}
        self.errors = 0
        self._queues: dict[str, deque[Scan]] = {}
        self._order: deque[str] = deque()  # robot ids in arrival order, one per queued scan
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._latest_maps: list[Any] = []
        self._worker = threading.Thread(target=self._work, name="server-core", daemon=True)

    # -- inputs (Zenoh threads) ------------------------------------------------------------
    def start(self) -> None:
        self.bus.declare_alive(keys.SERVER_ALIVE)
        self.bus.subscribe(keys.ALL_SCANS, Scan, self._on_scan)
        self.bus.subscribe(keys.ALL_TAGS, TagDetections, self._on_tags)
        self.bus.watch_alive(keys.ALL_ALIVE, self._on_alive)
        self.bus.serve(keys.SERVER_MAP, lambda: list(self._latest_maps))
        self._worker.start()

    def _on_scan(self, key: str, scan: Scan) -> None:
        try:
            self.registry.admit(keys.robot_id_of(key), scan.robot_id, "scan", scan.stamp_ns)
        except Refused:
            return
        with self._cv:
            q = self._queues.setdefault(scan.robot_id, deque())
            if len(q) >= self.cfg.queue_per_robot:
                q.popleft()  # the server is behind: the oldest waiting scan goes
                self.dropped[scan.robot_id] = self.dropped.get(scan.robot_id, 0) + 1
            else:
                self._order.append(scan.robot_id)
            q.append(scan)
            self._cv.notify()

    def _on_tags(self, key: str, msg: TagDetections) -> None:
        try:
            self.registry.admit(keys.robot_id_of(key), msg.robot_id, "tags", msg.stamp_ns)
        except Refused:
            return
        with self._cv:
            name = f"#tags:{msg.robot_id}"
            q = self._queues.setdefault(name, deque())
            if len(q) >= self.cfg.queue_per_robot:
                q.popleft()  # behind: the oldest sightings go first
                self.dropped[name] = self.dropped.get(name, 0) + 1
            else:
                self._order.append(name)
            q.append(msg)  # type: ignore[arg-type]
            self._cv.notify()

    def _on_alive(self, key: str, alive: bool) -> None:
        rid = keys.robot_id_of(key)
        if rid is None or not self.registry.set_alive(rid, alive):
            return
        with self._cv:
            self._queues.setdefault(f"#alive:{rid}", deque()).append(alive)  # type: ignore[arg-type]
            self._order.append(f"#alive:{rid}")
            self._cv.notify()

    # -- the worker ------------------------------------------------------------------------
    def _next(self, timeout_s: float) -> tuple[str, Any] | None:
        with self._cv:
            if not self._order and not self._cv.wait_for(lambda: bool(self._order), timeout_s):
                return None
            rid = self._order.popleft()
            return rid, self._queues[rid].popleft()

    def _work(self) -> None:
        next_states = 0.0
        last_stamp = map_stamp = 0
        while not self._stop.is_set():
            item = self._next(0.1)
            if item is not None:
                rid, payload = item
                try:
                    if rid.startswith("#alive:"):
                        self.core.set_alive(rid.split(":", 1)[1], bool(payload))
                    elif rid.startswith("#tags:"):
                        self.core.on_tags(payload)
                    else:
                        last_stamp = max(last_stamp, payload.stamp_ns)
                        cmd = self.core.on_scan(payload)
                        self.bus.publish(keys.robot_cmd_vel(rid), cmd, block=True)
                except Exception:
                    # one robot's failure must not stop the server for the others
                    self.errors += 1
                    log.exception("processing %s failed", rid)
            now = time.monotonic()
            try:
                for ev in self.core.pop_events():
                    self.bus.publish(keys.SERVER_EVENTS, ev, block=True)
                if now >= next_states:
                    next_states = now + self.cfg.states_period_s
                    self.bus.publish(keys.SERVER_ROBOTS, self.core.robot_states(last_stamp))
                if self.core.map_stamp_ns != map_stamp:
                    map_stamp = self.core.map_stamp_ns
                    self._latest_maps = self.core.map_updates()
                    for m in self._latest_maps:
                        self.bus.publish(keys.SERVER_MAP, m)
            except Exception:
                self.errors += 1
                log.exception("publishing server outputs failed")

    def stop(self) -> None:
        self._stop.set()
        if self._worker.is_alive():
            self._worker.join(timeout=10)

    def summary(self) -> dict[str, Any]:
        return {"registry": self.registry.counters(), "dropped_scans": self.dropped,
                "errors": self.errors, "bus": self.bus.stats.as_dict()}
