"""The server's outputs hold maps of the teams that exist: a team merged into another leaves
no map of its own behind (its last one was drawn in a team frame that no longer exists)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from server.planning import OccupancyGrid
from server.runtime.outputs import Outputs


def test_a_merged_teams_last_map_goes_at_the_next_write(tmp_path: Path) -> None:
    grid = OccupancyGrid(np.zeros((20, 30), np.int8), 0.1, (0.0, 0.0))
    cloud = np.zeros((5, 2))
    Outputs({"t1": grid, "t2": grid}, {"t1": lambda: cloud, "t2": lambda: cloud}, {},
            {}).write(tmp_path)
    assert (tmp_path / "maps" / "t2" / "map.yaml").is_file()
    # t2 merged into t1: the server no longer has a grid for it
    merged = {"merged_teams": {"t2": {"merged_into": "t1", "robot_ids": ["r2"]}}}
    Outputs({"t1": grid}, {"t1": lambda: cloud}, {}, merged).write(tmp_path)
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == ["t1"]
    assert (tmp_path / "maps" / "t1" / "map.yaml").is_file()
