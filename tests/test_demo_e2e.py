"""End to end on loopback: server, simulator and an agent as processes explore a small world."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from mrslam.demo import run

#: starts other processes (the CLI, the server, the simulator, agents, scripts): the e2e tier
pytestmark = pytest.mark.e2e


def write_map(folder: Path, name: str, img: np.ndarray, res: float) -> Path:
    """A nav2 map (``name``.pgm and .yaml) of ``img``, whose row 0 is the world's bottom."""
    cv2.imwrite(str(folder / f"{name}.pgm"), img[::-1])  # the image's first row is the top
    meta = {"image": f"{name}.pgm", "resolution": res, "origin": [0.0, 0.0, 0.0], "negate": 0,
            "occupied_thresh": 0.65, "free_thresh": 0.196, "mode": "trinary"}
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(meta))
    return path


def three_rooms(folder: Path) -> Path:
    """A 10 m × 6 m flat of three rooms whose doors are out of each other's sight; walls
    0.15 m thick (a nav2 map)."""
    res = 0.05
    img = np.full((int(7 / res), int(11 / res)), 205, np.uint8)  # outside: unknown

    def box(x0: float, y0: float, x1: float, y1: float, value: int) -> None:
        img[round(y0 / res):round(y1 / res), round(x0 / res):round(x1 / res)] = value

    t = 0.15
    box(0.5, 0.5, 10.5, 6.5, 0)
    box(0.5 + t, 0.5 + t, 10.5 - t, 6.5 - t, 254)
    box(4.5, 0.5, 4.5 + t, 6.5, 0)            # A | B+C
    box(4.5, 1.0, 4.5 + t, 2.0, 254)          # door A-B, low on the wall
    box(4.5, 3.5, 10.5, 3.5 + t, 0)           # B / C
    box(9.0, 3.5, 10.0, 3.5 + t, 254)         # door B-C, far right
    return write_map(folder, "flat", img, res)


def test_one_robot_explores_three_rooms_accurately(tmp_path: Path) -> None:
    world = three_rooms(tmp_path)
    report = run({"scenario": None, "world": str(world), "robots": {"r1": (1.5, 5.5, -0.5)},
                  "coverage": 0.97, "cells_per_m": 15, "max_sim_time_s": 400,
                  "wall_timeout_s": 240, "out": str(tmp_path / "run")}, progress=False)
    assert report["end"] == "finished", report["end"]
    assert report["reached"] and report["sim_time_to_threshold_s"] < 400
    assert report["robots"]["r1"]["distance_m"] > 8.0  # it had to go through both doors
    r1 = report["robots"]["r1"]
    assert r1["collisions"] == 0
    assert r1["max_position_error_m"] < 0.10
    assert r1["max_yaw_error_rad"] < 0.05
    assert report["true_coverage"] > 0.90
    assert report["phantom_area_m2"] < 1.0
    assert r1["bytes_sent"] > 0
    run_dir = tmp_path / "run"
    for f in ("report.json", "demo_config.yaml", "server/maps/team-r1/map.yaml",
              "server/maps/team-r1/points.ply", "coverage.png", "pose_error.png"):
        assert (run_dir / f).exists(), f


def test_two_robots_merge_over_the_wire(tmp_path: Path) -> None:
    """Two robots that start in sight of each other, as processes on loopback: the agents'
    detector reads the rendered tags, the server verifies and merges, and the report scores the
    merge against the ground truth. r2's own clock reads a date in 2027 and NTP sets it back an
    hour after 5 s: the server takes the first offset as it finds it, re-bases the step, and
    serves r2 throughout."""
    world = three_rooms(tmp_path)
    report = run({"scenario": None, "world": str(world),
                  "robots": {"r1": (1.5, 5.5, -0.5), "r2": (3.5, 4.5, 2.6)},
                  "clock_steps": {"r2": [(0.0, 1_800_000_000.0), (5.0, -3600.0)]},
                  "coverage": 0.97, "cells_per_m": 15, "max_sim_time_s": 300,
                  "wall_timeout_s": 240, "out": str(tmp_path / "run")}, progress=False)
    registry = json.loads((tmp_path / "run" / "server" / "summary.json").read_text())["registry"]
    assert registry["r2"]["clock_steps"] == 1 and registry["r2"].get("refused_out-of-order",
                                                                      0) <= 4
    assert registry["r2"]["clock_offset_s"] == pytest.approx(-1_800_000_000.0 + 3600.0,
                                                              abs=0.05)
    assert registry["r2"]["accepted_scan"] >= registry["r1"]["accepted_scan"] - 10
    assert report["end"] == "finished", report["end"]
    assert report["reached"]
    assert report["tag_counters"]["used"] > 0
    merges = [m for m in report["merges"] if not m["undone"]]
    assert len(merges) == 1 and report["false_merges"] == 0
    assert merges[0]["joint_error_m"] <= 0.05 and merges[0]["joint_error_deg"] <= 1.0
    # they start in sight of each other
    assert merges[0]["first_sight_s"] is not None
    assert merges[0]["first_sight_s"] <= min(1.0, merges[0]["sim_time_s"])
    final = [t for t in report["teams"].values() if not t.get("merged_into")]
    assert len(final) == 1 and sorted(final[0]["robot_ids"]) == ["r1", "r2"]
    # the bound for a small team (0.15 m): multi-process runs differ in when sightings
    # arrive, and here r2's drift along the rooms' axis peaked between 0.01 and 0.105 m in 9 runs
    for r in report["robots"].values():
        assert r["collisions"] == 0 and r["max_position_error_m"] < 0.15


def office_of_identical_rooms(folder: Path) -> Path:
    """A 15 m × 12 m office: a 3 m corridor between two rows of three rooms that look alike (same
    size, same table, door at the same place), so a map match can fit a room onto the wrong one;
    walls 0.1 m thick (a nav2 map)."""
    res = 0.05
    w, h, t = 15.0, 12.0, 0.1
    img = np.full((round(h / res), round(w / res)), 254, np.uint8)

    def box(x0: float, y0: float, x1: float, y1: float, value: int = 0) -> None:
        img[round(y0 / res):round(y1 / res), round(x0 / res):round(x1 / res)] = value

    box(0, 0, w, t), box(0, h - t, w, h), box(0, 0, t, h), box(w - t, 0, w, h)
    for y0, y1, door_y in ((0.0, 4.5, 4.5 - t), (7.5, h, 7.5)):
        box(0, door_y, w, door_y + t)                      # corridor wall
        for i in range(3):
            x = i * w / 3
            if i:
                box(x, y0, x + t, y1)                      # between rooms
            box(x + 1.0, door_y, x + 2.0, door_y + t, 254)  # door
            ty = (y0 + y1) / 2 - 0.4
            box(x + 2.5, ty, x + 3.7, ty + 0.8)            # table
    return write_map(folder, "office", img, res)


def test_three_robots_merge_correctly_among_identical_rooms(tmp_path: Path) -> None:
    """A world none of the tuning saw, with rooms that repeat and a fifth of the tag views drawn
    false: the team still forms from correct merges only and explores the office."""
    world = office_of_identical_rooms(tmp_path)
    report = run({"scenario": None, "world": str(world),
                  "robots": {"r1": (1.0, 6.0, 0.0), "r2": (14.0, 6.0, 3.1),
                             "r3": (6.0, 2.0, 1.57)},
                  "coverage": 0.95, "cells_per_m": 15, "spurious_detections": 0.2,
                  "max_sim_time_s": 600, "wall_timeout_s": 400,
                  "out": str(tmp_path / "run")}, progress=False)
    assert report["end"] == "finished", report["end"]
    assert report["false_merges"] == 0
    # the threshold is 95 % of free space and wall faces: free space itself is about as well
    # seen (0.96 in two runs; against free space alone, 0.95 left ~0.89 seen)
    assert report["reached"] and report["true_coverage"] >= 0.92
    merges = [m for m in report["merges"] if not m["undone"]]
    assert merges, "no merge"
    for m in merges:
        assert m["joint_error_m"] <= 0.1 and m["joint_error_deg"] <= 1.0, m
    for r in report["robots"].values():
        assert r["collisions"] == 0 and r["max_position_error_m"] < 0.15
