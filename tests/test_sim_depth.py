"""The depth camera as the simulator models it: a narrow fan looking along the robot's heading or
its tower's, no-returns past its range, noise growing with depth; chosen per robot on the
command line and in scenarios."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from schemas import ranges_from_mm
from sim.config import (
    SimConfig,
    parse_robot_arg,
    parse_robot_args,
    resolve_scene_sensors,
)
from sim.errors import SimError
from sim.process import depth_spec, params_from_config, step_messages
from sim.simulator import Simulator, TowerSpec
from tests.test_sim_scan import analytic, room

SEC = 1_000_000_000


def sweep_of(sim: Simulator, rid: str):  # type: ignore[no-untyped-def]
    msgs, _ = step_messages(sim, sim.sense(), "room")
    (sweep,) = [m for k, m in msgs if k.endswith(f"{rid}/lidar")]
    return sweep


def test_the_tower_rests_at_each_heading_then_turns_to_the_next() -> None:
    t = TowerSpec(positions=4, dwell_ns=SEC // 2, turn_ns=SEC // 2)
    assert t.yaw_at(0) == 0.0 and t.yaw_at(SEC // 2 - 1) == 0.0        # resting at 0°
    assert t.yaw_at(SEC // 2 + SEC // 4) == pytest.approx(math.pi / 4)  # half way to 90°
    assert t.yaw_at(SEC) == pytest.approx(math.pi / 2)                 # at 90°, resting
    assert t.yaw_at(3 * SEC) == pytest.approx(-math.pi / 2)            # 270°, wrapped
    assert t.yaw_at(4 * SEC) == 0.0                                     # round again


def test_a_depth_camera_sees_a_narrow_fan_to_its_range_with_noise_growing_with_depth() -> None:
    cfg = SimConfig()
    d = cfg.depth
    pose = (-1.7, 0.0, 0.0)          # looking along the room: the far wall 5.7 m away
    params = params_from_config(cfg, {"r1": "depth-fixed", "r2": "depth-fixed"})
    sim = Simulator(room(), {"r1": pose, "r2": (3.5, 2.5, math.pi)}, params, seed=4)
    near, far, seen = [], [], []
    for _ in range(30):
        s = sweep_of(sim, "r1")
        a = s.angles_rad()
        assert s.n_beams == d.beams and s.range_max_m == d.range_max_m
        assert a[0] == pytest.approx(-math.radians(d.hfov_deg) / 2)
        assert a[-1] == pytest.approx(math.radians(d.hfov_deg) / 2)
        r = ranges_from_mm(s.ranges_mm)
        truth = analytic(pose, a)
        ok = np.isfinite(r)
        assert np.all(truth[ok] < d.range_max_m + 0.2)     # nothing read beyond its range
        assert not np.any(ok & (truth > d.range_max_m + 0.3))
        z = truth * np.cos(a)                               # depth along the optical axis
        err = (r - truth) * np.cos(a)
        near += list(err[ok & (z < 1.7)])
        far += list(err[ok & (z > 2.4)])
        seen.append(ok.mean())
        sim.advance()
    assert 0.1 < np.mean(seen) < 0.9          # the side walls within range, the far one not
    # σ = σ0 + k z²: about 0.007 m at z ≈ 1.5 m, 0.026 m at z ≈ 2.6 m
    assert 2.0 < np.std(far) / np.std(near) < 8.0, (np.std(near), np.std(far))
    assert abs(np.mean(far)) < 0.01           # unbiased


def test_the_tower_turns_the_fan_and_the_sweep_says_where_it_looks() -> None:
    cfg = SimConfig()
    sim = Simulator(room(), {"r1": (1.0, 0.75, 0.3)}, params_from_config(cfg, {"r1": "depth"}),
                    seed=1)
    half = math.radians(cfg.depth.hfov_deg) / 2
    period = round((cfg.depth.dwell_s + cfg.depth.turn_s) / 0.1)
    heads = []
    for step in range(4 * period):
        s = sweep_of(sim, "r1")
        heads.append(s.angle_min_rad + half)
        r = ranges_from_mm(s.ranges_mm)
        truth = analytic((1.0, 0.75, 0.3), s.angles_rad())
        ok = np.isfinite(r)
        assert ok.sum() >= 5 and np.max(np.abs(r[ok] - truth[ok])) < 0.15, step
        sim.advance()
    rest = [heads[k * period] for k in range(4)]
    assert np.allclose(np.cos(rest), np.cos([0, math.pi / 2, math.pi, -math.pi / 2]),
                       atol=1e-9)


def test_a_lidar_robot_beside_a_depth_robot_keeps_its_360_degree_sweep() -> None:
    sim = Simulator(room(), {"r1": (0.0, 0.0, 0.0), "r2": (2.0, 1.0, 0.0)},
                    params_from_config(SimConfig(), {"r2": "depth"}), seed=2)
    s1, s2 = sweep_of(sim, "r1"), sweep_of(sim, "r2")
    assert s1.n_beams == 400 and s1.angle_min_rad == pytest.approx(-math.pi)
    assert s2.n_beams == SimConfig().depth.beams and s2.range_max_m == 3.0


def test_sensors_on_the_command_line() -> None:
    assert parse_robot_arg("r2:1.5,-2,0.5:depth") == ("r2", (1.5, -2.0, 0.5), "depth")
    assert parse_robot_arg("r2:1.5,-2") == ("r2", (1.5, -2.0, 0.0), None)
    robots, sensors = parse_robot_args(["r1:0,0", "r2:1,1,3.14:depth-fixed"])
    assert set(robots) == {"r1", "r2"} and sensors == {"r2": "depth-fixed"}
    with pytest.raises(SimError, match="unknown sensor 'sonar'"):
        parse_robot_arg("r2:1,2,0:sonar")
    with pytest.raises(SimError, match="given twice"):
        parse_robot_args(["r1:0,0", "r1:1,1"])


def test_sensors_in_scenarios(tmp_path: Path) -> None:
    world, robots, sensors = resolve_scene_sensors(SimConfig(scenario="mixed-2"))
    assert world.name == "small_house.world" and set(robots) == {"r1", "r2"}
    assert sensors == {"r2": "depth"}
    # the command line's sensor replaces the scenario's
    _, _, sensors = resolve_scene_sensors(SimConfig(scenario="mixed-2",
                                                    sensors={"r2": "lidar", "r1": "depth"}))
    assert sensors == {"r1": "depth"}
    with pytest.raises(SimError, match="r9, which is not a robot"):
        resolve_scene_sensors(SimConfig(scenario="mixed-2", sensors={"r9": "depth"}))
    bad = tmp_path / "scenarios.yaml"
    bad.write_text("cases:\n  x:\n    world: w.world\n    robots: {r1: [0, 0, 0]}\n"
                   "    sensors: {r1: radar}\n")
    with pytest.raises(SimError, match="scenario x: sensors must map"):
        resolve_scene_sensors(SimConfig(scenario="x", scenarios_file=str(bad)))


def test_a_fixed_camera_has_no_tower() -> None:
    cfg = SimConfig()
    assert depth_spec(cfg, "depth-fixed").tower is None
    tower = depth_spec(cfg, "depth").tower
    assert tower is not None and tower.positions == cfg.depth.tower_positions


def test_the_demo_hands_each_robots_sensor_to_the_simulator() -> None:
    from mrslam.demo import DemoConfig, plan_run, robot_args

    plan = plan_run(DemoConfig(scenario="mixed-2"))
    assert plan["sensors"] == {"r2": "depth"}
    assert robot_args(plan) == ["--robot", "r1:-8.0,9.0,0.0", "--robot", "r2:-3.0,9.0,4.7124:depth"]
    _, sensors = parse_robot_args(["r1:-8,9,0:depth-fixed", "r2:-3,9,0"])
    plan = plan_run(DemoConfig(scenario="mixed-2", robots={"r1": (-8.0, 9.0, 0.0),
                                                           "r2": (-3.0, 9.0, 0.0)},
                               sensors=sensors))
    assert plan["sensors"] == {"r1": "depth-fixed", "r2": "depth"}   # r2's from the scenario
    with pytest.raises(ValueError, match="sonar"):
        DemoConfig(sensors={"r1": "sonar"})  # type: ignore[dict-item]
