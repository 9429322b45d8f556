"""A robot that reboots mid-run: its agent killed with SIGKILL and started again, its odometry
back at zero. First the parts (the sim backend's odometry, the server's event when the robot
is placed again), then the whole demo with a robot rebooted."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import pytest

from robot_agent.sim_backend import SimBackend
from schemas import SimOdometry
from tests.test_server_reboot import run as run_core


class _Session:
    def declare_subscriber(self, key: str, handler: Any) -> Any:
        return None


class _Bus:
    session = _Session()


def _odometry(at_zero: bool) -> list[tuple[float, float, float]]:
    b = SimBackend(_Bus(), "r1", odometry_at_zero=at_zero)  # type: ignore[arg-type]
    for k, pose in enumerate([(2.0, 1.0, math.pi / 2), (2.0, 1.5, math.pi / 2),
                              (1.5, 1.5, math.pi)]):
        b._odometry(SimOdometry(robot_id="r1", seq=k, stamp_ns=(k + 1) * 100_000_000,
                                pose=pose))
    return [b.odometry_at(k * 100_000_000).pose for k in (1, 2, 3)]   # type: ignore[union-attr]


def test_odometry_starts_at_zero_where_a_rebooted_agent_first_hears_of_its_robot() -> None:
    assert _odometry(False)[0] == (2.0, 1.0, math.pi / 2)    # the simulator's, by default
    (x0, y0, t0), (x1, y1, t1), (x2, y2, t2) = _odometry(True)
    assert (x0, y0, t0) == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    assert (x1, y1, t1) == pytest.approx((0.5, 0.0, 0.0), abs=1e-12)   # 0.5 m on
    assert (x2, y2, t2) == pytest.approx((0.5, 0.5, math.pi / 2), abs=1e-12)


def test_the_server_tells_when_a_robot_back_after_a_reboot_is_placed_again() -> None:
    core, errors = run_core(0.25, 5.0)
    placed = [e for e in core.event_log if "placed again" in e.message]
    assert len(placed) == 1
    ev = placed[0]
    assert ev.kind == "robot_joined" and ev.robot_ids == ["r1"]
    assert ev.message == "robot r1 placed again in its map by scan 1 since it came back"
    assert ev.stamp_ns == 150 * 100_000_000 + 5_000_000_000    # the first scan after the gap
    assert not core.returning and max(errors[150:]) < 0.05


@pytest.mark.e2e
def test_a_robot_rebooted_mid_run_is_placed_again_and_the_run_goes_on(tmp_path: Path) -> None:
    from mrslam.demo import run

    report = run({"scenario": "small-house-3", "reboot": {"r2": 30.0}, "reboot_s": 2.0,
                  "record": False, "max_sim_time_s": 200, "wall_timeout_s": 150,
                  "out": str(tmp_path / "run")}, progress=False)
    [rb] = report["agent_reboots"]
    assert rb["robot_id"] == "r2" and rb["killed_sim_s"] >= 30.0
    assert rb["new_pid"] != rb["pid"] and rb["back_seq"] == 0   # a new agent's first scan
    assert rb["back_odom"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)   # odometry from zero
    back = rb["back_sim_s"]
    assert back > rb["killed_sim_s"]
    events = [e for e in report["events"] if e["robot_ids"] == ["r2"]]
    assert any(e["kind"] == "robot_lost" for e in events)
    placed = [e for e in events if "placed again" in e["message"]]
    assert len(placed) == 1 and placed[0]["stamp_ns"] * 1e-9 - back <= 10.0
    m = re.search(r"by scan (\d+)", placed[0]["message"])
    assert m is not None and int(m.group(1)) <= 100
    assert report["end"] == "finished" and report["reached"]
    assert report["false_merges"] == 0
    assert report["robots"]["r2"]["max_position_error_m"] < 0.15   # before and after
