"""Sections of ``bench/hostile.py`` that attack the server's admission and clocks.

- ``fake_ids``: a server process (open: no robot list) gets one scan each from 2,000 robot ids
  nobody runs, then a real robot joins; is it served, how many log lines, how much memory?
- ``clocks``: two robots stream to a server on this machine's clock; one's clock steps back an
  hour, and a scan an hour ahead is sent under the other's name. How long is each without an
  answer, and what did the server count?
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from schemas import keys
from tests.fleet import RoomRobot, ServerProcess, room_scan, rss_mb

HOUR_NS = 3600 * 1_000_000_000
GOAL_LOG_LINES = 200


def fake_ids(folder: Path, n_fakes: int = 2000) -> dict[str, Any]:
    srv = ServerProcess(folder, {"explore": {"total_area_m2": 48.0}})
    try:
        with srv.client() as bus:
            rss0 = rss_mb(srv.proc.pid)
            bus.wait_for_subscribers(keys.robot_scan("f0"), 10.0)
            t0 = time.monotonic()
            for i in range(n_fakes):
                bus.publish(keys.robot_scan(f"f{i}"), room_scan(f"f{i}", 0, time.time_ns(), 0.0))
            send_s = time.monotonic() - t0
            time.sleep(2.0)
            robot = RoomRobot(srv.endpoint, "r1").start()
            t1 = time.monotonic()
            first = None
            while time.monotonic() < t1 + 15.0:
                if first is None and robot.answered_since(t1):
                    first = time.monotonic() - t1
                time.sleep(0.05)
            answered = robot.answered_since(t1)
            silence = robot.longest_silence_s(t1 + 2.0, time.monotonic())
            robot.close()
            rss1 = rss_mb(srv.proc.pid)
    finally:
        code = srv.stop()
    lines = srv.log_lines()
    summary = json.loads((folder / "server" / "summary.json").read_text())
    tracebacks = sum("Traceback" in ln for ln in lines)
    return {
        "fake_ids": n_fakes, "send_s": round(send_s, 2),
        "real_robot_first_answer_s": None if first is None else round(first, 3),
        "real_robot_answers_in_15_s": answered,
        "real_robot_longest_silence_s": round(silence, 3),
        "log_lines": len(lines), "tracebacks": tracebacks,
        "rss_growth_mb": round(rss1 - rss0, 1), "admission": summary["admission"],
        "exit_code": code,
        "goal_met": first is not None and answered >= 100 and len(lines) <= GOAL_LOG_LINES
        and tracebacks == 0 and code == 0,
    }


def clocks(folder: Path) -> dict[str, Any]:
    srv = ServerProcess(folder, {"explore": {"total_area_m2": 48.0}})
    try:
        with srv.client() as bus:
            r1 = RoomRobot(srv.endpoint, "r1").start()
            r2 = RoomRobot(srv.endpoint, "r2").start()
            time.sleep(4.0)
            t_step = time.monotonic()
            r1.clock_offset_ns = -HOUR_NS
            bus.publish(keys.robot_scan("r2"),
                        room_scan("r2", 10**6, time.time_ns() + HOUR_NS, 0.0))
            time.sleep(10.0)
            t_end = time.monotonic()
            out = {
                "r1_clock_step_s": -3600.0,
                "r1_longest_silence_s": round(r1.longest_silence_s(t_step, t_end), 3),
                "r2_longest_silence_s": round(r2.longest_silence_s(t_step, t_end), 3),
                "r1_answers_after_step": r1.answered_since(t_step),
            }
            r1.close()
            r2.close()
    finally:
        code = srv.stop()
    summary = json.loads((folder / "server" / "summary.json").read_text())
    reg = summary["registry"]
    out |= {"registry": {r: reg.get(r, {}) for r in ("r1", "r2")}, "exit_code": code,
            "server_errors": summary["errors"]}
    out["goal_met"] = (out["r1_longest_silence_s"] < 3.0 and out["r2_longest_silence_s"] < 1.0
                       and reg["r1"].get("clock_steps") == 1 and code == 0)
    return out


SECTIONS = {"fake_ids": fake_ids, "clocks": clocks}
