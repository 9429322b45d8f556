"""nav2 maps from the one writer (``schemas.nav2map``), read back the way nav2's map_server
reads them in trinary mode, give exactly the cells written — from each of the three places that
write maps (the server's team maps, ``slam-log``'s map, the simulator's true maps)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from schemas import nav2map
from schemas.occupancy import OCCUPIED, UNKNOWN
from server.planning import OccupancyGrid as PlanningGrid
from server.runtime.outputs import write_nav2_grid
from server.slam.export import write_nav2 as write_slam_map
from server.slam.grid import GridParams
from server.slam.grid import OccupancyGrid as SlamGrid
from sim.grid import OccupancyGrid as SimGrid
from sim.grid import write_nav2 as write_sim_map

FREE_C, OCC_C, UNKNOWN_C = 0, 100, -1   # map_server's OccupancyGrid values


def map_server_load(yaml_path: Path) -> tuple[np.ndarray, dict]:
    """map_server's trinary load: int8 cells (row 0 = lowest y), as nav2 fills them."""
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta["mode"] == "trinary"
    img = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.ndim == 2 and img.dtype == np.uint8
    p = (255.0 - img.astype(np.float64)) / 255.0
    if meta.get("negate", 0):
        p = 1.0 - p
    cells = np.full(img.shape, UNKNOWN_C, np.int8)
    cells[p > meta["occupied_thresh"]] = OCC_C
    cells[p < meta["free_thresh"]] = FREE_C
    return cells[::-1], meta


def random_masks(seed: int, shape: tuple[int, int] = (37, 53)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    kind = rng.integers(0, 3, shape)   # 0 free, 1 occupied, 2 unknown
    return kind == 0, kind == 1


def expected(free: np.ndarray, occupied: np.ndarray) -> np.ndarray:
    cells = np.full(free.shape, UNKNOWN_C, np.int8)
    cells[free] = FREE_C
    cells[occupied] = OCC_C
    return cells


def test_pixel_values_sit_well_away_from_the_thresholds() -> None:
    ps = {v: (255 - v) / 255 for v in (nav2map.FREE_PIXEL, nav2map.UNKNOWN_PIXEL,
                                       nav2map.OCCUPIED_PIXEL)}
    margin = 0.05
    assert ps[nav2map.FREE_PIXEL] < nav2map.FREE_THRESH - margin
    assert nav2map.FREE_THRESH + margin < ps[nav2map.UNKNOWN_PIXEL]
    assert ps[nav2map.UNKNOWN_PIXEL] < nav2map.OCCUPIED_THRESH - margin
    assert ps[nav2map.OCCUPIED_PIXEL] > nav2map.OCCUPIED_THRESH + margin


@pytest.mark.parametrize("fmt", ["png", "pgm"])
@pytest.mark.parametrize("seed", range(5))
def test_the_writer_round_trips_through_map_server(tmp_path: Path, seed: int, fmt: str) -> None:
    free, occupied = random_masks(seed)
    path = nav2map.write(tmp_path, "m", free, occupied, 0.05, (-1.5, 2.0), formats=(fmt,))
    cells, meta = map_server_load(path)
    assert np.array_equal(cells, expected(free, occupied))
    assert meta["image"] == f"m.{fmt}" and meta["origin"] == [-1.5, 2.0, 0.0]
    assert not list(tmp_path.glob(".*.tmp"))


def test_the_server_team_map_round_trips(tmp_path: Path) -> None:
    free, occupied = random_masks(11)
    data = np.where(occupied, OCCUPIED, np.where(free, 0, UNKNOWN)).astype(np.int8)
    grid = PlanningGrid(data, 1 / 15, (0.3, -0.7))
    cells, meta = map_server_load(write_nav2_grid(grid, tmp_path))
    assert np.array_equal(cells, expected(grid.free, grid.occupied))
    assert np.array_equal(cells, expected(free, occupied))
    assert meta["resolution"] == pytest.approx(1 / 15)


def test_the_slam_map_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    grid = SlamGrid.from_dense(GridParams(resolution_m=0.05), (1.0, 2.0),
                               rng.normal(0.0, 3.0, (30, 40)), rng.random((30, 40)) < 0.7)
    cells, _ = map_server_load(write_slam_map(grid, tmp_path, "map"))
    assert np.array_equal(cells, expected(grid.free_mask(), grid.occupied_mask()))
    assert (cells == UNKNOWN_C).any() and (cells == FREE_C).any() and (cells == OCC_C).any()


def test_the_simulator_true_map_round_trips(tmp_path: Path) -> None:
    free, occupied = random_masks(5)
    data = np.where(occupied, OCCUPIED, np.where(free, 0, UNKNOWN)).astype(np.int8)
    cells, meta = map_server_load(write_sim_map(SimGrid(data, 0.05, (0.0, 0.0, 0.0)), tmp_path))
    assert np.array_equal(cells, data)
    assert meta["image"] == "map.pgm" and (tmp_path / "map.png").exists()


def test_all_writers_agree_on_thresholds(tmp_path: Path) -> None:
    free, occupied = random_masks(1, (4, 4))
    data = np.where(occupied, OCCUPIED, np.where(free, 0, UNKNOWN)).astype(np.int8)
    metas = [yaml.safe_load(p.read_text()) for p in (
        write_nav2_grid(PlanningGrid(data, 0.05, (0.0, 0.0)), tmp_path / "a"),
        write_slam_map(SlamGrid(GridParams(), (0.0, 0.0), (4, 4)), tmp_path / "b"),
        write_sim_map(SimGrid(data, 0.05, (0.0, 0.0, 0.0)), tmp_path / "c"))]
    assert {(m["free_thresh"], m["occupied_thresh"], m["negate"], m["mode"]) for m in metas} \
        == {(nav2map.FREE_THRESH, nav2map.OCCUPIED_THRESH, 0, "trinary")}


def test_masks_of_different_shapes_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="masks"):
        nav2map.write(tmp_path, "m", np.zeros((2, 3), bool), np.zeros((3, 2), bool), 0.05,
                      (0, 0))
    with pytest.raises(ValueError, match="formats"):
        nav2map.write(tmp_path, "m", np.zeros((2, 3), bool), np.zeros((2, 3), bool), 0.05,
                      (0, 0), formats=("jpg",))
