"""Stopping a run from outside (issue 42, finding 6): SIGTERM, or SIGINT without a terminal,
stops every process ``mrslam demo`` started within 5 s and the report is still written; a
demo killed with SIGKILL leaves no process behind either; ``mrslam server`` stops with its
planner and map-match processes within 5 s."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest

from bench.support import stopping
from bench.support.fleet import RoomRobot
from schemas.bus import BusError, free_local_endpoint
from tests.waiting import within

pytestmark = pytest.mark.e2e

#: the demo, its server, three agents and the simulator
DEMO_PROCESSES = 6


def _demo(tmp_path: Path, sigint_ignored: bool = False) -> tuple[stopping.Run, Path]:
    out = tmp_path / "run"
    run = stopping.start(["demo", "--out", str(out), "--no-record"], tmp_path / "demo.log",
                         sigint_ignored=sigint_ignored)
    assert run.wait_for(DEMO_PROCESSES, 120.0), run.log()[-2000:]
    truth = out / "sim" / "truth.jsonl"   # under way: the robots move
    assert within(lambda: truth.exists() and truth.stat().st_size > 10_000, 120.0)
    return run, out


@pytest.mark.parametrize("sig,sigint_ignored", [(signal.SIGTERM, False),
                                                (signal.SIGINT, True)],
                         ids=["sigterm", "sigint-without-terminal"])
def test_a_stop_signal_ends_every_process_of_the_demo_and_the_report_is_written(
        tmp_path: Path, sig: signal.Signals, sigint_ignored: bool) -> None:
    run, out = _demo(tmp_path, sigint_ignored)
    result = stopping.stop(run, sig)
    assert result["alive_after_5_s"] == [], result
    assert result["exit_code"] == 128 + sig.value, run.log()[-2000:]   # as a shell says it
    assert f"mrslam: demo: stopped by {sig.name}" in run.log()
    report = json.loads((out / "report.json").read_text())
    assert report["end"] == f"stopped by {sig.name}"
    assert report["stopped_by"] == sig.name
    assert set(report["robots"]) == {"r1", "r2", "r3"}
    assert any("figures" in m for m in report["missing"])


def test_a_killed_demo_leaves_no_process_behind(tmp_path: Path) -> None:
    run, out = _demo(tmp_path)
    result = stopping.stop(run, signal.SIGKILL)
    assert result["alive_after_5_s"] == [], result
    # each child noticed and stopped itself: the server wrote its outputs on the way out
    summary = json.loads((out / "server" / "summary.json").read_text())
    assert "running" not in summary


def test_the_server_stops_with_its_planner_and_map_match_processes(tmp_path: Path) -> None:
    import yaml

    endpoint = free_local_endpoint()
    cfg = {"bus": {"mode": "router", "listen": [endpoint], "connect": []},
           "explore": {"total_area_m2": 48.0}, "out": str(tmp_path / "server")}
    (tmp_path / "server.yaml").write_text(yaml.safe_dump(cfg))
    run = stopping.start(["server", "-c", str(tmp_path / "server.yaml")],
                         tmp_path / "server.log")
    robots: list[RoomRobot] = []
    try:
        for rid in ("r1", "r2"):    # two robots apart: two teams, so a map-match process too
            assert within(lambda r=rid: _join(robots, endpoint, r), 60.0), run.log()
        # the server, its planner and map-match processes (and multiprocessing's tracker)
        assert run.wait_for(4, 60.0), run.processes()
        result = stopping.stop(run, signal.SIGTERM)
    finally:
        for robot in robots:
            robot.close()
    assert result["alive_after_5_s"] == [], result
    assert result["exit_code"] == 0, run.log()[-2000:]
    summary = json.loads((tmp_path / "server" / "summary.json").read_text())
    assert "running" not in summary


def _join(robots: list[RoomRobot], endpoint: str, rid: str) -> bool:
    try:
        robots.append(RoomRobot(endpoint, rid).start())
    except BusError:
        time.sleep(0.2)
        return False
    return True
