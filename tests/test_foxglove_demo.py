"""A demo's run.mcap, end to end: two robots merge over the wire, and the recording's Foxglove
channels decode with the SDK's schemas, draw no point for a beam without a return, come with
a transform tree for every scan, and hang from one root after the merge."""

from __future__ import annotations

from pathlib import Path

import pytest

from mrslam.demo import run
from tests.test_demo_e2e import three_rooms
from tests.test_foxglove_channels import check_foxglove

pytestmark = pytest.mark.e2e


def test_a_demo_recording_draws_in_foxglove(tmp_path: Path) -> None:
    world = three_rooms(tmp_path)
    report = run({"scenario": None, "world": str(world),
                  "robots": {"r1": (1.5, 5.5, -0.5), "r2": (3.5, 4.5, 2.6)},
                  "coverage": 0.97, "cells_per_m": 15, "max_sim_time_s": 300,
                  "wall_timeout_s": 240, "out": str(tmp_path / "run")}, progress=False)
    assert report["end"] == "finished" and len(report["merges"]) == 1
    got = check_foxglove(tmp_path / "run" / "run.mcap")
    for name in ("LaserScan", "FrameTransforms", "Grid", "PoseInFrame", "PosesInFrame", "Log"):
        assert got["messages"].get(f"foxglove.{name}", 0) > 0, name
    assert got["no_return_drawn_as_points"] == 0
    assert got["scans"] > 100 and got["scans_without_transform"] == 0
    assert got["merges"] == 1 and got["tree_messages_after_last_merge"] > 100
    assert got["max_roots_after_last_merge"] == 1 and got["roots_at_end"] == ["team-r1"]
    # a robot not yet placed (its first estimate after a merge in the first second): briefly
    assert got["tree_messages_with_a_robot_not_yet_placed"] < \
        0.1 * got["tree_messages_after_last_merge"]
    for rid in ("r1", "r2"):
        assert (tmp_path / "run" / "server" / "trajectories" / f"{rid}_final.tum").exists()
        assert (tmp_path / "run" / "sim" / "trajectories" / f"{rid}_truth.tum").exists()
