"""Agents that reboot mid-run, as a robot that loses power would (the demo's ``reboot``)."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mrslam.launch import GroupClosed, ProcessGroup

if TYPE_CHECKING:
    from mrslam.monitor import Monitor

log = logging.getLogger(__name__)


class Reboots:
    """Reboots agents as a robot that loses power would: once the simulation passes a robot's
    time its agent is killed with SIGKILL, and ``down_s`` (wall clock) later it is started
    again with ``agent_<id>_rebooted.yaml``, its odometry back at zero. One row per reboot in
    ``rows`` (simulated times as the bus's clock showed them): when it was killed, when it
    was started again, and the stamp (and odometry) of its first scan after that (when it was
    back)."""

    def __init__(self, procs: ProcessGroup, mon: Monitor, at_s: dict[str, float],
                 down_s: float, out: Path) -> None:
        from schemas import Scan, keys

        self.procs, self.mon, self.down_s, self.out = procs, mon, down_s, out
        self.rows: list[dict[str, Any]] = []
        self._plan = sorted(at_s.items(), key=lambda kv: kv[1])
        self._waiting: dict[str, dict[str, Any]] = {}   # robot -> its row, until it is back
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="reboots", daemon=True)
        if self._plan:
            for rid, _ in self._plan:
                mon.bus.subscribe(keys.robot_scan(rid), Scan, self._on_scan)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30.0)

    def _on_scan(self, key: str, msg: Any) -> None:
        with self._lock:
            row = self._waiting.pop(msg.robot_id, None)
            if row is not None:
                row.update(back_sim_s=round(msg.stamp_ns * 1e-9, 3), back_seq=msg.seq,
                           back_odom=[round(v, 4) for v in msg.odom_pose])

    def _run(self) -> None:
        for rid, at_s in self._plan:
            while self.mon.sim_time_s < at_s:
                if self._stop.wait(0.02):
                    return
            p = next(q for q in self.procs.procs if q.name == f"agent_{rid}")
            if self._stop.is_set() or p.stopping or not p.alive():
                return
            row: dict[str, Any] = {"robot_id": rid, "at_s": at_s,
                                   "killed_sim_s": round(self.mon.sim_time_s, 3),
                                   "pid": p.pid}
            self.rows.append(row)
            p.popen.kill()   # SIGKILL
            p.popen.wait()
            if self._stop.wait(self.down_s):
                return
            with self._lock:
                self._waiting[rid] = row
            try:
                self.procs.restart(p, ("agent", "-c",
                                       str(self.out / f"agent_{rid}_rebooted.yaml")))
            except GroupClosed:   # the run is stopping
                return
            row.update(restarted_sim_s=round(self.mon.sim_time_s, 3), new_pid=p.pid)
            log.warning("rebooted the agent of %s: killed at %.1f s of sim time, started "
                        "again at %.1f s (pid %d)", rid, row["killed_sim_s"],
                        row["restarted_sim_s"], p.pid)
