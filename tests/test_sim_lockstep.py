"""Lockstep: with a server in the loop, one seed gives bit-identical ground truth and scans."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from schemas import Scan, SimGroundTruth, TagDetections, VelocityCommand, encode, keys
from schemas.bus import Bus
from sim.simulator import SimParams, Simulator
from sim.world import World
from tests.test_agent_loopback import running
from tests.waiting import within

ROBOTS = {"r1": (-8.0, 9.0, 0.0), "r2": (-6.2, 8.3, 3.0)}  # in one room, facing each other
STEPS = 50


def steer(scan: Scan) -> tuple[float, float]:
    """A deterministic reactive driver: forward unless something is close ahead."""
    r = scan.ranges_m()
    a = scan.angles_rad()
    ahead = np.min(np.where(np.abs(a) < 0.5, r, np.inf))
    return (0.0, 0.8) if ahead < 0.8 else (0.35, 0.15)


Run = tuple[bytes, list[tuple[str, int, tuple[float, float, float], bytes]], list[bytes]]


def lockstep_run(endpoint: str, router: Bus, out: Path, seed: int, delay_s: float = 0.0,
                 first_delay_s: float = 0.0, agents: dict[str, Any] | None = None) -> Run:
    """(truth.jsonl, scans, tag detections) of one lockstep run with a server in the loop that
    answers each scan after ``delay_s`` of wall time (the first one after ``first_delay_s``)."""
    scans: list[tuple[str, int, tuple[float, float, float], bytes]] = []
    tags: list[bytes] = []

    def server(key: str, scan: Scan) -> None:  # answers every scan at once, stamped with it
        first = not any(s[0] == scan.robot_id for s in scans)
        scans.append((scan.robot_id, scan.stamp_ns, scan.odom_pose, scan.ranges_mm))
        v, w = steer(scan)
        time.sleep(first_delay_s if first else delay_s)
        router.publish(keys.robot_cmd_vel(scan.robot_id), VelocityCommand(
            robot_id=scan.robot_id, stamp_ns=scan.stamp_ns, v_mps=v, omega_rps=w, ttl_s=0.5))

    subs = [router.subscribe(keys.ALL_SCANS, Scan, server),
            router.subscribe(keys.ALL_TAGS, TagDetections, lambda k, m: tags.append(encode(m)))]
    token = router.declare_alive(keys.SERVER_ALIVE)
    try:
        with running(endpoint, ROBOTS, {"lockstep": True, "seed": seed, "max_steps": STEPS,
                                        "out": str(out)}, agent_overrides=agents) as results:
            assert within(lambda: "sim" in results, 60.0)  # it stops itself at max_steps
    finally:
        token.undeclare()
        for s in subs:
            s.undeclare()
    sim = results["sim"]
    assert sim["steps"] == STEPS and sim["ack_timeouts"] == 0
    assert all(results[rid].get("command_timeouts", 0) == 0 for rid in ROBOTS)
    return (out / "truth.jsonl").read_bytes(), sorted(scans), sorted(tags)


def test_two_lockstep_runs_with_one_seed_are_identical(router: Bus, endpoint: str,
                                                       tmp_path: Path) -> None:
    truth_a, scans_a, tags_a = lockstep_run(endpoint, router, tmp_path / "a", seed=7)
    # a slow server changes nothing: every step waits for its command
    truth_b, scans_b, tags_b = lockstep_run(endpoint, router, tmp_path / "b", seed=7,
                                            delay_s=0.01)
    assert truth_a == truth_b
    assert len(scans_a) == len(ROBOTS) * STEPS and scans_a == scans_b
    assert tags_a and tags_a == tags_b  # the same images, so the same detections
    lines = [msgspec.json.decode(line, type=SimGroundTruth) for line in truth_a.splitlines()]
    assert [t.seq for t in lines] == list(range(STEPS))
    assert all(p.distance_m > 0.5 for p in lines[-1].poses)  # they moved under the commands
    assert any(t.relatives for t in lines)                   # and saw each other's tags
    # a server slow to answer its first scan (starting on a busy machine) changes nothing
    # either: the agents wait longer for a server's first command than for the others
    truth_d, scans_d, _ = lockstep_run(endpoint, router, tmp_path / "d", seed=7,
                                       first_delay_s=1.2,
                                       agents={"lockstep": {"command_timeout_s": 0.5}})
    assert truth_d == truth_a and scans_d == scans_a
    # a different seed gives other sensor noise
    _, scans_c, _ = lockstep_run(endpoint, router, tmp_path / "c", seed=8)
    assert [s[3] for s in scans_c] != [s[3] for s in scans_a]


def test_simulator_core_is_deterministic_per_robot_stream() -> None:
    world = World.from_shapes("box", "test", [np.array([[3, -3], [4, -3], [4, 3], [3, 3.0]])],
                              [])

    def run(spawn: dict[str, tuple[float, float, float]], seed: int) -> list[np.ndarray]:
        sim = Simulator(world, spawn, SimParams(), seed)
        out = []
        for k in range(20):
            sim.set_command("r1", 0.2, 0.3 * math.sin(k / 3))
            obs = sim.sense()
            out.append(np.concatenate([obs.ranges_m["r1"], obs.odometry["r1"][0]]))
            sim.advance()
        return out

    a = run({"r1": (0.0, 0.0, 0.0)}, 3)
    b = run({"r1": (0.0, 0.0, 0.0)}, 3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    # another robot far away changes neither r1's noise nor its odometry
    c = run({"r1": (0.0, 0.0, 0.0), "r9": (-20.0, 0.0, 0.0)}, 3)
    assert all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))
