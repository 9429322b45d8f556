"""The worlds that ship with the package: our floor plans, the dissertation's facts.

Each case's robots stand in free space, the houses are closed, and every room can be reached
through openings a robot fits through, so coverage can reach the cases' thresholds.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from schemas.occupancy import FREE
from sim import floorplan
from sim.config import DEFAULT_SCENARIOS, SimConfig, load_scenario, resolve_scene_sensors
from sim.errors import SimError
from sim.grid import OccupancyGrid, rasterise
from sim.loader import load_world
from sim.world import World
from tests.conftest import DATA

#: the house scenarios, and the dissertation's case whose poses and settings each takes
CASES = {"small-house-1": "thesis-case-1", "small-house-3": "thesis-case-2",
         "large-house-1": "thesis-case-3", "large-house-5": "thesis-case-4"}
SIZE_M = {"small_house.world": 20.0, "large_house.world": 50.0}
RESOLUTION_M = 0.05


def clearance_m(world: World, x: float, y: float) -> float:
    """Distance from (x, y) to the nearest wall or pillar face [m]."""
    seg = world.segments
    a, e = seg[:, :2], seg[:, 2:] - seg[:, :2]
    t = np.clip(((np.array([x, y]) - a) * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
    return float(np.hypot(*(a + t[:, None] * e - (x, y)).T).min())


def test_the_packaged_files_are_what_the_floor_plans_write() -> None:
    for name, make in floorplan.PLANS.items():
        path = floorplan.WORLDS_DIR / f"{name}.world"
        assert path.read_text() == floorplan.to_sdf(make()), "run python -m sim.floorplan"
    assert DEFAULT_SCENARIOS.parent == floorplan.WORLDS_DIR


@pytest.mark.parametrize("name", sorted(SIZE_M))
def test_walls_have_the_dissertations_thickness_and_height_and_doors_fit_a_robot(
        name: str) -> None:
    root = ET.parse(floorplan.WORLDS_DIR / name).getroot()
    sizes = [[float(v) for v in (el.text or "").split()]
             for el in root.iter("size")]
    walls = [s for s in sizes if s[0] != s[1]]     # the rest are square pillars
    assert len(walls) >= 20
    assert all(s[1] == pytest.approx(0.15) for s in walls)
    assert all(s[2] == pytest.approx(2.5) for s in sizes)
    plan = floorplan.PLANS[name.removesuffix(".world")]()
    doors = [w for wall in plan.walls for _, w in wall.doors]
    assert len(doors) >= 10 and min(doors) >= 0.9
    slanted = [w for w in plan.walls if w.a[0] != w.b[0] and w.a[1] != w.b[1]]
    assert len(slanted) >= 2


def assert_every_room_reachable(grid: OccupancyGrid, robots: dict[str, Any],
                                resolution_m: float) -> None:
    """A disc of 0.4 m fits everywhere it must go: the cells that far from any wall form one
    region holding every robot, and that region grown back by 0.4 m covers the free space."""
    free = (grid.cells == FREE).astype(np.uint8)
    dist = cv2.distanceTransform(free, cv2.DIST_L2, 5) * resolution_m
    roomy = (dist >= 0.4).astype(np.uint8)
    _, labels = cv2.connectedComponents(roomy, connectivity=8)
    cells = grid.world_to_cell(np.array([p[:2] for p in robots.values()]))
    region = {int(labels[r, c]) for r, c in cells}
    assert len(region) == 1 and 0 not in region
    reach = (labels == region.pop()).astype(np.uint8)
    grown = cv2.dilate(reach, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (17, 17)))
    assert (grown & free).sum() >= 0.995 * free.sum()


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_case_spawns_in_free_space_of_a_closed_connected_house(case: str) -> None:
    world_path, robots, _ = resolve_scene_sensors(SimConfig(scenario=case))
    world = load_world(world_path)
    # the dissertation's dimensions: a square of 20 or 50 m about the origin
    size = SIZE_M[world_path.name]
    xmin, ymin, xmax, ymax = world.bounds()
    assert xmax - xmin == pytest.approx(size, abs=0.1) and ymax - ymin == pytest.approx(
        size, abs=0.1)
    assert abs(xmin + xmax) < 0.1 and abs(ymin + ymax) < 0.1
    grid = rasterise(world, RESOLUTION_M)
    free = (grid.cells == FREE).astype(np.uint8)
    # closed: the enclosed free space is nearly the whole floor (a leak to the outside would
    # leave almost none of it)
    assert free.sum() * RESOLUTION_M**2 > 0.85 * size**2
    assert_every_room_reachable(grid, robots, RESOLUTION_M)
    for rid, (x, y, _) in robots.items():
        assert clearance_m(world, x, y) >= 0.4, f"{case} {rid} stands {clearance_m(world, x, y)}"


@pytest.mark.skipif(not (DATA / "worlds" / "thesis").is_dir(), reason="no ../shared/data")
@pytest.mark.parametrize("case", sorted(CASES))
def test_the_cases_keep_the_dissertations_poses_areas_and_settings(case: str) -> None:
    ours = load_scenario(DEFAULT_SCENARIOS, case)
    assert ours["settings_from"] == CASES[case]
    theirs = load_scenario(DATA / "worlds" / "thesis" / "scenarios.yaml", CASES[case])
    for key in ("robots", "total_area_m2", "coverage_threshold", "grid_cells_per_m", "lambda",
                "v_mps", "omega_max_rps", "lookahead_m"):
        assert ours[key] == theirs[key], key
    assert "reported" not in ours   # its figures were measured in its worlds, not ours
    cases = yaml.safe_load(DEFAULT_SCENARIOS.read_text())["cases"]
    assert set(CASES) <= set(cases)   # (the package also ships worlds of its own)
    # the dissertation's names stay with the dissertation's worlds
    assert not any(name.startswith("thesis-case") for name in cases)


def test_an_old_name_fails_with_the_new_one() -> None:
    """A name the packaged houses had when they were named after the dissertation's cases
    fails in one line naming the new one: run under the old name, our building would pass
    for the dissertation's."""
    renamed = yaml.safe_load(DEFAULT_SCENARIOS.read_text())["renamed"]
    assert renamed == {v: k for k, v in CASES.items()}
    for old, new in renamed.items():
        with pytest.raises(SimError, match=f"'{old}' is called '{new}' now") as e:
            load_scenario(DEFAULT_SCENARIOS, old)
        assert "\n" not in str(e.value)
