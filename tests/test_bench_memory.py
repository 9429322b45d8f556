"""bench/memory.py end to end on a short mission: it prints one JSON row per part and a summary,
with resident memory against simulated time and what the keyframes keep in memory and on disk."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent


def test_a_short_mission_prints_memory_against_time_and_keyframes_on_disk(
        tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "memory.py"), "--only", "mission",
         "--scenario", "small-house-3", "--robots", "1", "--sim-hours", "0.01",
         "--every-s", "12", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]
    mission, summary = rows[0], rows[-1]["summary"]
    assert mission["part"] == "mission" and "error" not in mission, mission
    times = [t for t, _ in mission["samples_t_s_rss_mb"]]
    assert times[0] == 0 and times[-1] >= 36 and times == sorted(times)
    assert all(m > 50 for _, m in mission["samples_t_s_rss_mb"])      # MB, not kB or bytes
    assert mission["keyframes"]["r1"] > 3
    # the keyframes' map points went to the unlinked file, not into memory
    assert mission["keyframes_on_disk_mb"] > 0 and mission["keyframes_in_memory_mb"] > 0
    assert not mission["robot_goal_met"]                # a goal for two hours, not 36 s
    assert summary["mission_per_robot_end_mb"] == mission["per_robot_end_mb"]
    assert (tmp_path / "mission").is_dir()
