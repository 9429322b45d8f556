"""``mrslam demo``: the main job.

The exploration demo (server + simulator + agents on loopback) is not built yet. Until it is,
the demo runs the most complete thing that exists: the bus check, in which a router session and
three robot client sessions on loopback exchange scans, commands and the map at 10 Hz, and the
figures are written to a run folder.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel
from rich.console import Console
from rich.table import Table

from mrslam.config import write_resolved

log = logging.getLogger(__name__)


class BusCheckConfig(BaseModel):
    scenario: str = "thesis-case-2"
    robots: list[str] = ["r1", "r2", "r3"]
    duration_s: float = 3.0
    rate_hz: float = 10.0
    beams: int = 400


def run(scenario: str = "thesis-case-2", out: Path | None = None) -> dict[str, Any]:
    console = Console(stderr=True)
    console.print("[bold]mrslam demo[/]: the exploration demo is not built yet; "
                  "running the bus check (router + 3 robot clients on loopback).")
    cfg = BusCheckConfig(scenario=scenario)
    run_dir = out or Path("runs") / time.strftime("demo-%Y%m%d-%H%M%S")
    write_resolved(cfg, run_dir)
    report = bus_check(cfg)
    (run_dir / "report.json").write_text(json.dumps(report, indent=2))
    table = Table(title="bus check")
    for col in ("robot", "scans sent", "scans received", "commands received"):
        table.add_column(col)
    for rid, row in report["robots"].items():
        table.add_row(rid, str(row["scans_sent"]), str(row["scans_received"]),
                      str(row["commands_received"]))
    console.print(table)
    console.print(f"map query answered: {report['map_query_ok']}; run folder: {run_dir}")
    return report


def bus_check(cfg: BusCheckConfig) -> dict[str, Any]:
    from schemas import MapUpdate, Scan, VelocityCommand, keys, quantise_ranges_mm
    from schemas.bus import Bus, free_local_endpoint

    endpoint = free_local_endpoint()
    rng = np.random.default_rng(0)
    scans: dict[str, int] = dict.fromkeys(cfg.robots, 0)
    cmds: dict[str, int] = dict.fromkeys(cfg.robots, 0)
    with Bus.open("router", listen=[endpoint]) as server:
        clients = {r: Bus.open("client", connect=[endpoint]) for r in cfg.robots}
        try:
            def on_scan(key: str, msg: Scan) -> None:
                scans[msg.robot_id] += 1
                server.publish(keys.robot_cmd_vel(msg.robot_id),
                               VelocityCommand(robot_id=msg.robot_id, v_mps=0.3, omega_rps=0.0,
                                               seq=msg.seq, stamp_ns=time.time_ns()))

            server.subscribe(keys.ALL_SCANS, Scan, on_scan)
            grid = np.full((300, 300), -1, np.int8)
            server.serve(keys.SERVER_MAP, lambda: [MapUpdate.from_grid(
                grid, team_id="t1", robot_ids=cfg.robots, resolution_m=0.05,
                origin=(-7.5, -7.5, 0.0))])
            for rid, bus in clients.items():
                def on_cmd(key: str, msg: VelocityCommand, rid: str = rid) -> None:
                    cmds[rid] += 1
                bus.subscribe(keys.robot_cmd_vel(rid), VelocityCommand, on_cmd)
            time.sleep(0.3)
            n = int(cfg.duration_s * cfg.rate_hz)
            for i in range(n):
                for rid, bus in clients.items():
                    ranges = rng.uniform(0.5, 9.0, cfg.beams)
                    bus.publish(keys.robot_scan(rid), Scan(
                        robot_id=rid, seq=i, stamp_ns=time.time_ns(), odom_pose=(0.0, 0.0, 0.0),
                        angle_min_rad=-np.pi, angle_increment_rad=2 * np.pi / cfg.beams,
                        range_min_mm=50, range_max_mm=10000,
                        ranges_mm=quantise_ranges_mm(ranges, 0.05, 10.0)))
                time.sleep(1.0 / cfg.rate_hz)
            time.sleep(0.3)
            maps = clients[cfg.robots[0]].get(keys.SERVER_MAP, MapUpdate)
        finally:
            for bus in clients.values():
                bus.close()
    return {
        "mode": "bus-check",
        "robots": {r: {"scans_sent": n, "scans_received": scans[r], "commands_received": cmds[r]}
                   for r in cfg.robots},
        "map_query_ok": len(maps) == 1 and maps[0].grid().shape == (300, 300),
    }
