"""A server killed with SIGKILL and started again on its state folder resumes: the same robots
with their keyframes, and it serves the robots that kept running through the outage."""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from tests.waiting import within

pytestmark = pytest.mark.e2e

CONFIG = {"robots": ["r1", "r2"], "outputs_period_s": 0.5}


def summary(folder: Path) -> dict[str, Any]:
    return dict(json.loads((folder / "server" / "summary.json").read_text()))


def keyframes(folder: Path) -> dict[str, int]:
    try:
        return {rid: r["keyframes"] for rid, r in summary(folder)["robots"].items()}
    except (OSError, ValueError, KeyError):
        return {}


def test_a_server_killed_with_sigkill_resumes_from_its_journal(tmp_path: Path) -> None:
    srv = ServerProcess(tmp_path, CONFIG)
    servers = [srv]
    srv.client().close()
    robots = [RoomRobot(srv.endpoint, rid).start() for rid in ("r1", "r2")]
    try:
        # outputs are written while the server runs: there is something before the kill
        assert within(lambda: min(keyframes(tmp_path).values(), default=0) >= 3, 60)
        srv.proc.send_signal(signal.SIGKILL)
        srv.proc.wait(timeout=10)
        srv.stop()
        before = keyframes(tmp_path)            # the last set written, whole
        assert summary(tmp_path)["running"] is True
        assert (tmp_path / "server" / "state" / "journal-0001.mcap").stat().st_size > 0
        # the same port again, so the robots that kept running find it
        srv2 = ServerProcess(tmp_path, {**CONFIG, "bus": {"listen": [srv.endpoint]}})
        servers.append(srv2)
        srv2.endpoint = srv.endpoint
        t_restart = time.monotonic()
        srv2.client().close()
        assert within(lambda: all(r.answered_since(t_restart) > 10 for r in robots), 60)
        assert within(lambda: summary(tmp_path).get("resumed", {}).get("entries", 0) > 0, 30)
        resumed = summary(tmp_path)["resumed"]
        assert resumed["robots"] == ["r1", "r2"] and resumed["unreadable"] == 0
        after = keyframes(tmp_path)
        assert all(after[rid] >= before[rid] for rid in before)   # not from zero
        assert srv2.stop() == 0
        assert (tmp_path / "server" / "state" / "journal-0002.mcap").exists()
        assert any("resumed from" in line for line in srv2.log_lines())
    finally:
        for r in robots:
            r.close()
        for s in servers:
            s.stop()
