"""The operator's orders inside the core: a stop holds a robot at zero whatever else would move
it, a resume lets it go on, a bad order is refused with its reason, and the orders come back
from the journal after a restart."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas import Scan, TagDetections
from server.command.operator import OperatorCommand, OperatorError, parse
from server.core import ServerCore
from server.exploration.navigator import NavMode
from server.runtime.journal import JournalWriter, replay
from server.runtime.snapshot import Snapshots
from tests.test_server_journal import config, messages

STOP_ALL = OperatorCommand("stop")
RESUME_ALL = OperatorCommand("resume")


def run(core: ServerCore, msgs: list[Scan | TagDetections],
        journal: JournalWriter | None = None) -> list[tuple[str, float, float]]:
    """Feed the messages as the worker does; the commands (robot, v, ω) it answered with."""
    out = []
    for m in msgs:
        if isinstance(m, Scan):
            if journal is not None:
                journal.scan(m, m.stamp_ns)
            cmd = core.on_scan(m, m.stamp_ns)
            out.append((m.robot_id, cmd.v_mps, cmd.omega_rps))
        else:
            if journal is not None:
                journal.tags(m)
            core.on_tags(m)
    return out


def order(core: ServerCore, cmd: OperatorCommand, journal: JournalWriter | None = None,
          stamp_ns: int = 0) -> tuple[int, str]:
    if journal is not None:
        journal.operator(cmd, stamp_ns)
    return core.operate(cmd, stamp_ns)


@pytest.fixture(scope="module")
def steps() -> list[Scan | TagDetections]:
    return messages(160)


def moving(cmds: list[tuple[str, float, float]]) -> int:
    return sum(1 for _, v, w in cmds if abs(v) > 1e-9 or abs(w) > 1e-9)


def test_a_stop_all_holds_every_robot_at_zero_until_resumed(
        steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    before = run(core, steps[:120])
    assert moving(before) > 0                      # they were being driven
    status, line = order(core, STOP_ALL)
    assert status == 200 and "held" in line
    held = run(core, steps[120:240])
    assert len(held) > 50 and moving(held) == 0
    states = core.robot_states(0)
    assert {r.mode for r in states.robots} == {"idle"}
    ev = [e for e in core.pop_events() if e.kind == "operator"]
    assert ev and "stop every robot" in ev[-1].message
    assert order(core, RESUME_ALL)[0] == 200
    after = run(core, steps[240:])
    assert moving(after) > 0


def test_a_stop_wins_over_a_recovery_manoeuvre(steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    run(core, steps[:60])
    r1 = core.robots["r1"]
    r1.nav.recovery.start(steps[60].stamp_ns * 1e-9, np.zeros((0, 2)))
    r1.nav.mode = NavMode.RECOVERING
    assert order(core, OperatorCommand("stop", "r1"))[0] == 200
    cmds = run(core, steps[60:140])
    assert moving([c for c in cmds if c[0] == "r1"]) == 0
    assert moving([c for c in cmds if c[0] == "r2"]) > 0   # only r1 was stopped


def test_bad_orders_are_refused_with_their_reason(steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    run(core, steps[:80])
    status, line = order(core, OperatorCommand("stop", "r9"))
    assert status == 404 and "no robot r9" in line and "r1, r2" in line
    order(core, STOP_ALL)
    status, line = order(core, OperatorCommand("resume", "r1"))
    assert status == 409 and "stop-all" in line
    status, line = order(core, OperatorCommand("goto", "r1", (500.0, 500.0)))
    assert status == 409 and "no way for r1" in line
    assert core.orders.refused == 3 and core.orders.applied == 1
    assert core.orders.holds("r1") and core.orders.holds("r2")


def test_a_goto_plans_a_path_and_the_robot_follows_it(steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    run(core, steps[:120])
    r1 = core.robots["r1"]
    goal = (float(r1.pose[0]) + 0.6, float(r1.pose[1]))
    status, line = order(core, OperatorCommand("goto", "r1", goal))
    assert status == 200, line
    est = {r.robot_id: r for r in core.robot_states(0).robots}["r1"]
    assert est.mode == "returning" and est.target == pytest.approx(goal)
    cmds = run(core, steps[120:140])
    assert moving([c for c in cmds if c[0] == "r1"]) > 0
    # a stop wins over the errand too
    order(core, OperatorCommand("stop", "r1"))
    cmds = run(core, steps[140:180])
    assert moving([c for c in cmds if c[0] == "r1"]) == 0


def test_a_robot_goes_home_once_its_team_is_done(steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    run(core, steps[:100])
    assert order(core, OperatorCommand("home", None, on=True))[0] == 200
    for team in core.teams.values():
        team.finished = True
    run(core, steps[100:102])
    errands = core.orders.errands
    assert set(errands) == {"r1", "r2"} and {e.kind for e in errands.values()} == {"home"}
    # the team frame is r1's first pose; r2 started 5 m ahead of it and 3 m to its right
    # (SPAWN, both facing +y)
    assert math.dist(errands["r1"].goal_xy, (0.0, 0.0)) < 0.1
    assert math.dist(errands["r2"].goal_xy, (3.0, -5.0)) < 0.3
    assert any("returns to its start" in ev.message for ev in core.pop_events())


def test_orders_come_back_from_the_journal(tmp_path: Path,
                                           steps: list[Scan | TagDetections]) -> None:
    core = ServerCore(config())
    journal = JournalWriter(tmp_path)
    run(core, steps[:100], journal)
    order(core, OperatorCommand("stop", "r2"), journal, steps[99].stamp_ns)
    order(core, OperatorCommand("home", "r1", on=True), journal, steps[99].stamp_ns)
    run(core, steps[100:140], journal)
    Snapshots(tmp_path).commit(Snapshots(tmp_path).prepare(core, journal.sequence))
    order(core, STOP_ALL, journal, steps[139].stamp_ns)
    run(core, steps[140:150], journal)
    journal.close()

    fresh = ServerCore(config())
    report = replay(fresh, tmp_path)
    assert report.unreadable == 0
    assert fresh.orders.view() == core.orders.view()
    assert fresh.orders.stop_all and fresh.orders.holds("r1")
    cmds = run(fresh, steps[150:170])
    assert cmds and moving(cmds) == 0

    loaded = Snapshots(tmp_path).load()           # the snapshot, then the journal after it
    assert loaded is not None
    resumed, since = loaded
    assert resumed.orders.holds("r2") and not resumed.orders.stop_all
    replay(resumed, tmp_path, from_sequence=since)
    assert resumed.orders.view() == core.orders.view()


@pytest.mark.parametrize(("data", "field"), [
    ("stop", "a command is a JSON object"),
    ({}, "action"),
    ({"action": "explode"}, "action"),
    ({"action": "stop", "robot_id": "r 1"}, "robot_id"),
    ({"action": "stop", "robot_id": 7}, "robot_id"),
    ({"action": "stop", "extra": 1}, "unknown field"),
    ({"action": "goto", "point": [1, 2]}, "robot_id"),
    ({"action": "goto", "robot_id": "r1"}, "point"),
    ({"action": "goto", "robot_id": "r1", "point": [1]}, "point"),
    ({"action": "goto", "robot_id": "r1", "point": ["1", 2]}, "point"),
    ({"action": "goto", "robot_id": "r1", "point": [math.nan, 2]}, "point"),
    ({"action": "goto", "robot_id": "r1", "point": [1e9, 2]}, "point"),
    ({"action": "goto", "robot_id": "r1", "point": [True, 2]}, "point"),
    ({"action": "stop", "point": [1, 2]}, "point"),
    ({"action": "home", "on": "yes"}, "on"),
])
def test_a_malformed_order_names_its_problem(data: Any, field: str) -> None:
    with pytest.raises(OperatorError, match=field) as e:
        parse(data)
    assert e.value.status == 400


def test_orders_round_trip_through_their_journal_form() -> None:
    for cmd in (STOP_ALL, OperatorCommand("stop", "r1"), OperatorCommand("resume", "r2"),
                OperatorCommand("goto", "r1", (1.5, -2.25)),
                OperatorCommand("home", "r3", on=False), OperatorCommand("home", None, on=True)):
        assert parse(cmd.as_dict()) == cmd
