"""What a resumed server says (issue 42, finding 8): on a run that had finished, why it stops
at once; with a changed configuration, which settings the resumed run keeps as they were."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from bench.support.fleet import RoomRobot, ServerProcess
from tests.waiting import within

pytestmark = pytest.mark.e2e

#: a room of 48 m² against 10 m² to cover: the first map finishes the run
FINISHING = {"robots": ["r1"], "exit_when_done": True,
             "explore": {"total_area_m2": 10.0, "coverage_threshold": 0.5}}


def _serve_until_exit(folder: Path, cfg: dict[str, Any]) -> ServerProcess:
    srv = ServerProcess(folder, cfg)
    srv.client().close()
    robot = RoomRobot(srv.endpoint, "r1").start()
    try:
        srv.proc.wait(timeout=120)
    finally:
        robot.close()
        srv.stop()
    return srv


def test_a_server_resumed_on_a_finished_run_says_why_it_stops(tmp_path: Path) -> None:
    first = _serve_until_exit(tmp_path, FINISHING)
    assert first.proc.returncode == 0, first.log_lines()[-20:]
    again = ServerProcess(tmp_path, FINISHING)
    try:
        again.proc.wait(timeout=120)
    finally:
        code = again.stop()
    assert code == 0
    said = [ln for ln in again.log_lines() if "already finished" in ln]
    assert len(said) == 1, again.log_lines()[-20:]
    assert "(team-r1: team coverage reached at " in said[0], said[0]
    assert "exit_when_done" in said[0] and "state_dir" in said[0]


def test_a_changed_configuration_names_the_settings_the_resumed_run_keeps(
        tmp_path: Path) -> None:
    cfg: dict[str, Any] = {"robots": ["r1"], "snapshot_period_s": 1.0}
    srv = ServerProcess(tmp_path, cfg)
    srv.client().close()
    robot = RoomRobot(srv.endpoint, "r1").start()
    try:
        state = tmp_path / "server" / "state"
        assert within(lambda: any(state.glob("snapshot-*.pkl")), 60.0)
    finally:
        robot.close()
        assert srv.stop() == 0
    changed = {**cfg, "outputs_period_s": 3.0,    # this start's own: not named
               "explore": {"coverage_threshold": 0.7, "lam": 0.2, "seek_lam": 0.1},
               "control": {"v_mps": 0.25, "omega_max_rps": 1.0},
               "slam": {"grid": {"resolution_m": 0.1}}}
    again = ServerProcess(tmp_path, changed)
    try:
        again.client().close()
    finally:
        assert again.stop() == 0
    said = [ln for ln in again.log_lines() if "configuration differs" in ln]
    assert len(said) == 1, again.log_lines()[-20:]
    line = said[0]
    assert "in 6 setting(s)" in line and "and 2 more" in line, line
    assert "explore.coverage_threshold (0.98 → 0.7)" in line, line
    assert "outputs_period_s" not in line
