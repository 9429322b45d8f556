"""End to end: ``mrslam demo --map`` starts server, simulator and agents on a known map; robots
spawned where the server is not told are placed in it over the wire, the map is left as it was
(localize) with one mission more, and a path with no map is refused in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.support.known_mission import WORLDS, free_poses
from bench.support.survey import survey_map
from mrslam.demo import WORLD_FRAME, run
from server.knownmap.ghosts import MAP_TEAM
from server.runtime.mapstore import read_map, write_map

#: starts other processes (the CLI, the server, the simulator, agents, scripts): the e2e tier
pytestmark = pytest.mark.e2e

HOUSE = WORLDS / "small_house.world"
ROOT = Path(__file__).resolve().parent.parent


def test_robots_spawned_anywhere_are_placed_in_the_known_map_over_the_wire(
        tmp_path: Path) -> None:
    known = survey_map(HOUSE)
    known.notes[WORLD_FRAME] = "0 0 0"           # surveyed in the world's frame: scored there
    write_map(known, tmp_path / "yesterday" / "known_map", site="small_house")
    spawns = free_poses(HOUSE, 2, np.random.default_rng(7))
    report = run({"scenario": None, "world": str(HOUSE),
                  "robots": {f"r{i + 1}": tuple(float(v) for v in p)
                             for i, p in enumerate(spawns)},
                  "map": str(tmp_path / "yesterday"), "max_sim_time_s": 30,
                  "wall_timeout_s": 240, "out": str(tmp_path / "run")}, progress=False)
    assert report["end"] == "finished", report["end"]    # localize: done once all are placed
    team = report["teams"].get(MAP_TEAM)
    assert team is not None, list(report["teams"])
    assert set(team["robot_ids"]) >= {"r1", "r2"}, team["robot_ids"]   # both placed
    for rid in ("r1", "r2"):
        assert report["robots"][rid]["max_position_error_m"] < 0.10, report["robots"][rid]
    left = read_map(tmp_path / "run" / "server" / "known_map", site="small_house")
    assert len(left) == len(known) and left.missions == known.missions + 1
    np.testing.assert_allclose(left.poses, known.poses, atol=1e-3)   # localize: unchanged


def test_a_demo_on_a_path_without_a_map_is_refused_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "mrslam", "demo", "--map", str(tmp_path / "none"),
         "--out", str(tmp_path / "run")], cwd=ROOT, capture_output=True, text=True,
        timeout=120)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "no such folder" in lines[0], proc.stderr
