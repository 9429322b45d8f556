"""Sections of ``bench/hostile.py`` that stop a run from outside, as systemd, a CI runner or a
user's ``kill`` does (issue 42, finding 6). The processes of a run are found by a tag in their
environment (``bench/support/stopping.py``), wherever they were re-parented.

- ``stop_demo``: the default demo (three robots, lockstep, recorded) gets a signal at a random
  moment of its first ``max_delay_s``: SIGTERM, SIGINT without a terminal, SIGHUP, or SIGKILL
  (after which its children must notice by themselves). Goal: no process of the run alive 5 s
  later, and ``report.json`` written (not after SIGKILL: nothing is left to write it).
- ``stop_server``: ``mrslam server`` serving two robots in real time (so with a planner and a
  map-match process) gets SIGTERM; then a server resuming a long journal (every snapshot
  removed, so it replays the whole of a demo's run) gets SIGTERM while it replays. Goal: every
  process of it gone within 5 s.
"""

from __future__ import annotations

import json
import random
import shutil
import signal
import socket
import time
from pathlib import Path
from typing import Any

import yaml

from bench.support import stopping
from bench.support.fleet import RoomRobot
from schemas.bus import BusError, free_local_endpoint

GOAL_S = 5.0
#: the signals tried, in turn; True: SIGINT as a shell's background job gets it (ignored)
KINDS: list[tuple[signal.Signals, bool]] = [
    (signal.SIGTERM, False), (signal.SIGINT, True), (signal.SIGTERM, False),
    (signal.SIGHUP, False), (signal.SIGKILL, False), (signal.SIGTERM, False)]


def stop_demo(folder: Path, runs: int = 6, max_delay_s: float = 45.0, seed: int = 42
              ) -> dict[str, Any]:
    rng = random.Random(seed)
    rows = []
    for i in range(runs):
        sig, ignored = KINDS[i % len(KINDS)]
        # from 1.5 s: before that the demo is still importing and has started nothing
        delay = round(rng.uniform(1.5, max_delay_s), 1)
        out = folder / f"run{i}"
        run = stopping.start(["demo", "--out", str(out)], folder / f"run{i}.log",
                             sigint_ignored=ignored)
        time.sleep(delay)
        row = {"delay_s": delay, "sigint_ignored": ignored,
               **stopping.stop(run, sig, within_s=GOAL_S)}
        row["report_written"] = (out / "report.json").exists()
        if row["report_written"]:
            report = json.loads((out / "report.json").read_text())
            row["end"] = report["end"]
            row["sim_time_s"] = report["sim_time_s"]
        rows.append(row)
    alive = sum(len(r[f"alive_after_{GOAL_S:g}_s"]) for r in rows)
    no_report = [i for i, r in enumerate(rows)
                 if not r["report_written"] and r["signal"] != "SIGKILL"]
    return {"runs": rows, "processes_alive_after_5_s": alive,
            "all_gone_s_max": max((r["all_gone_s"] or 1e9) for r in rows),
            "demo_exit_s_max": max((r["command_exit_s"] or 1e9) for r in rows
                                   if r["signal"] != "SIGKILL"),
            "runs_without_report": no_report,
            "goal_met": alive == 0 and not no_report}


def stop_server(folder: Path, journal_from: Path | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"serving": _serving(folder / "serving")}
    journal = journal_from or _longest_journal(folder.parent / "stop_demo")
    if journal is not None:
        out["resuming"] = _resuming(folder / "resuming", journal)
    cases = [v for v in out.values() if isinstance(v, dict)]
    out["goal_met"] = all(c[f"alive_after_{GOAL_S:g}_s"] == [] for c in cases)
    return out


def _server(folder: Path, cfg: dict[str, Any]) -> stopping.Run:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "server.yaml").write_text(yaml.safe_dump(cfg))
    return stopping.start(["server", "-c", str(folder / "server.yaml")], folder / "server.log")


def _serving(folder: Path) -> dict[str, Any]:
    endpoint = free_local_endpoint()
    run = _server(folder, {"bus": {"mode": "router", "listen": [endpoint], "connect": []},
                           "explore": {"total_area_m2": 48.0}, "out": str(folder / "server")})
    robots: list[RoomRobot] = []
    deadline = time.monotonic() + 60.0
    while len(robots) < 2 and time.monotonic() < deadline:
        try:
            robots.append(RoomRobot(endpoint, f"r{len(robots) + 1}").start())
        except BusError:
            time.sleep(0.2)
    run.wait_for(4, 60.0)      # the server, its planner and map-match processes, the tracker
    time.sleep(3.0)
    try:
        return stopping.stop(run, signal.SIGTERM, within_s=GOAL_S)
    finally:
        for robot in robots:
            robot.close()


def _longest_journal(demos: Path) -> Path | None:
    journals = sorted(demos.glob("run*/server/state/journal-*.mcap"),
                      key=lambda p: p.stat().st_size)
    return journals[-1] if journals else None


def _resuming(folder: Path, journal: Path) -> dict[str, Any]:
    """A server on ``journal``'s run with no snapshot: it replays the whole journal. The
    signal comes once it listens (it opens the bus first, then loads its state)."""
    source = journal.parent.parent.parent        # the demo's run folder
    cfg = yaml.safe_load((source / "server.yaml").read_text())
    cfg["out"] = str(folder / "server")
    endpoint = free_local_endpoint()
    cfg["bus"]["listen"] = [endpoint]
    state = folder / "server" / "state"
    shutil.rmtree(state, ignore_errors=True)
    state.mkdir(parents=True)
    shutil.copy(journal, state / journal.name)
    if (journal.parent / "blobs.bin").exists():
        shutil.copy(journal.parent / "blobs.bin", state / "blobs.bin")
    run = _server(folder, cfg)
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline and run.proc.poll() is None:
        with socket.socket() as s:
            if s.connect_ex((host, int(port))) == 0:
                break
        time.sleep(0.1)
    time.sleep(0.5)
    replaying = "resumed from" not in run.log()
    return {"journal_bytes": journal.stat().st_size, "replaying_at_signal": replaying,
            **stopping.stop(run, signal.SIGTERM, within_s=GOAL_S)}


SECTIONS = {"stop_demo": stop_demo, "stop_server": stop_server}
