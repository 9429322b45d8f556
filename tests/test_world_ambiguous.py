"""The self-similar world (``ambiguous_wings``): it loads, its west wing is the mirror image of
its east wing (and the building looks the same turned by half a turn) except at the few
features meant to tell them apart, those features are there, and the ``ambiguous-*``
scenarios start their robots in free space at poses whose surroundings look alike."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest

from schemas.occupancy import FREE, OCCUPIED
from sim import floorplan
from sim.config import DEFAULT_SCENARIOS, SimConfig, load_scenario, resolve_scene_sensors
from sim.errors import WorldError
from sim.grid import OccupancyGrid, rasterise
from sim.loader import load_world
from sim.world import World
from tests.test_packaged_worlds import assert_every_room_reachable, clearance_m

WORLD = floorplan.WORLDS_DIR / "ambiguous_wings.world"
SCENARIOS = ["ambiguous-2", "ambiguous-3"]
RES_M = 0.05
#: cells (of RES_M) a wall may sit off its mirror image from rasterising alone
TOLERANCE_CELLS = 2
#: how far around a symmetry-breaking feature its mirror image may differ [m]
BREAK_RADIUS_M = 2.5


@pytest.fixture(scope="module")
def world() -> World:
    return load_world(WORLD)


@pytest.fixture(scope="module")
def grid(world: World) -> OccupancyGrid:
    return rasterise(world, RES_M)


def occupied_at(grid: OccupancyGrid, xy: np.ndarray) -> np.ndarray:
    """Whether each world point (..., 2) falls in an occupied cell (outside the grid: no)."""
    shape = xy.shape[:-1]
    rc = grid.world_to_cell(xy.reshape(-1, 2))
    h, w = grid.shape
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
    out = np.zeros(len(rc), bool)
    out[inside] = grid.cells[rc[inside, 0], rc[inside, 1]] == OCCUPIED
    return out.reshape(shape)


def lattice(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Points RES_M apart on cell centres, symmetric about 0 where the bounds are."""
    xs = np.arange(x0 + RES_M / 2, x1, RES_M)
    ys = np.arange(y0 + RES_M / 2, y1, RES_M)
    return np.stack(np.meshgrid(xs, ys), axis=-1)


def mismatch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Occupied points of one picture farther than TOLERANCE_CELLS from any of the other's."""
    k = np.ones((2 * TOLERANCE_CELLS + 1,) * 2, np.uint8)
    da = cv2.dilate(a.astype(np.uint8), k).astype(bool)
    db = cv2.dilate(b.astype(np.uint8), k).astype(bool)
    return (a & ~db) | (b & ~da)


def near(pts: np.ndarray, centres: list[tuple[float, float]], r: float) -> np.ndarray:
    out = np.zeros(pts.shape[:-1], bool)
    for cx, cy in centres:
        out |= np.hypot(pts[..., 0] - cx, pts[..., 1] - cy) <= r
    return out


def test_the_shipped_file_is_what_the_floor_plan_writes() -> None:
    assert WORLD.read_text() == floorplan.to_sdf(floorplan.ambiguous_wings()), \
        "run python -m sim.floorplan"
    assert floorplan.PLANS["ambiguous_wings"] is floorplan.ambiguous_wings


def test_it_is_a_closed_30_m_square_with_the_other_worlds_walls_and_doors(
        world: World, grid: OccupancyGrid) -> None:
    xmin, ymin, xmax, ymax = world.bounds()
    assert xmax - xmin == pytest.approx(30.0, abs=0.05)
    assert ymax - ymin == pytest.approx(30.0, abs=0.05)
    assert abs(xmin + xmax) < 0.05 and abs(ymin + ymax) < 0.05
    root = ET.parse(WORLD).getroot()
    sizes = [[float(v) for v in (el.text or "").split()] for el in root.iter("size")]
    walls = [s for s in sizes if s[0] != s[1]]
    assert len(walls) >= 100
    assert all(s[1] == pytest.approx(0.15) for s in walls)
    assert all(s[2] == pytest.approx(2.5) for s in sizes)
    doors = [w for wall in floorplan.ambiguous_wings().walls for _, w in wall.doors]
    assert len(doors) >= 36 and min(doors) >= 1.2
    # closed: the enclosed free space is nearly the whole floor
    assert grid.area_m2(FREE) > 0.8 * 30.0**2


def test_the_west_wing_is_the_mirror_image_of_the_east_wing_but_for_the_breaks(
        grid: OccupancyGrid) -> None:
    pts = lattice(-15.5, 15.5, -15.5, 15.5)
    here = occupied_at(grid, pts)
    mirrored = occupied_at(grid, pts * np.array([-1.0, 1.0]))
    breaks = [(x, y) for _, x, y in floorplan.AMBIGUOUS_BREAKS]
    # a break shows where it is and where its mirror image is
    zone = near(pts, breaks + [(-x, y) for x, y in breaks], BREAK_RADIUS_M)
    bad = mismatch(here, mirrored)
    assert here.sum() > 10000   # the walls are there to compare
    assert not (bad & ~zone).any(), \
        f"{int((bad & ~zone).sum())} cells break the mirror symmetry outside the breaks"
    # and each break does break it
    for what, x, y in floorplan.AMBIGUOUS_BREAKS:
        own = near(pts, [(x, y)], BREAK_RADIUS_M)
        assert (bad & own).sum() >= 10, f"the {what} is mirrored: it breaks nothing"


def test_half_a_turn_and_a_corridor_over_look_the_same_but_for_the_breaks(
        grid: OccupancyGrid) -> None:
    pts = lattice(-15.5, 15.5, -15.5, 15.5)
    here = occupied_at(grid, pts)
    turned = occupied_at(grid, -pts)
    breaks = [(x, y) for _, x, y in floorplan.AMBIGUOUS_BREAKS]
    zone = near(pts, breaks + [(-x, -y) for x, y in breaks], BREAK_RADIUS_M)
    bad = mismatch(here, turned)
    assert not (bad & ~zone).any()
    assert all((bad & near(pts, [(x, y)], BREAK_RADIUS_M)).sum() >= 10 for x, y in breaks)
    # the east wing's middle corridor and its rooms, and the south corridor 10 m away (no
    # break there): the corridors repeat
    band = lattice(2.0, 14.5, -4.5, 4.5)
    shifted = occupied_at(grid, band + np.array([0.0, -10.0]))
    assert not mismatch(occupied_at(grid, band), shifted).any()


def test_the_breaks_are_solid(world: World, grid: OccupancyGrid) -> None:
    plan = floorplan.ambiguous_wings()
    for what, x, y in floorplan.AMBIGUOUS_BREAKS:
        assert occupied_at(grid, np.array([[x, y]]))[0], f"no {what} at ({x}, {y})"
    assert plan.pillars and all(abs(px) > 0.3 for px, _, _ in plan.pillars)


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_scenarios_spawn_in_free_space_of_one_connected_building(
        name: str, world: World, grid: OccupancyGrid) -> None:
    case = load_scenario(DEFAULT_SCENARIOS, name)
    assert case["world"] == WORLD.name and case["coverage_threshold"] == 0.90
    path, robots, _ = resolve_scene_sensors(SimConfig(scenario=name))
    assert path == WORLD and len(robots) == int(name.rsplit("-", 1)[1])
    assert_every_room_reachable(grid, robots, RES_M)
    for rid, (x, y, _) in robots.items():
        assert clearance_m(world, x, y) >= 0.9, f"{name} {rid}"
    xs = [p[0] for p in robots.values()]
    assert min(xs) < -1.5 and max(xs) > 1.5, "robots in both wings"


def surroundings(grid: OccupancyGrid, pose: tuple[float, float, float],
                 radius_m: float) -> np.ndarray:
    """Occupancy of the disc about a pose, in the pose's own frame (what a robot's first map
    there holds, at most)."""
    pts = lattice(-radius_m, radius_m, -radius_m, radius_m)
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    world_pts = np.stack([x + c * pts[..., 0] - s * pts[..., 1],
                          y + s * pts[..., 0] + c * pts[..., 1]], axis=-1)
    return occupied_at(grid, world_pts) & (np.hypot(pts[..., 0], pts[..., 1]) <= radius_m)


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_robots_start_at_mirror_images_whose_surroundings_look_alike(
        name: str, grid: OccupancyGrid) -> None:
    _, robots, _ = resolve_scene_sensors(SimConfig(scenario=name))
    r1, r2 = robots["r1"], robots["r2"]
    # mirror images in the plane x = 0
    assert r2[0] == pytest.approx(-r1[0]) and r2[1] == pytest.approx(r1[1])
    assert math.cos(r2[2]) == pytest.approx(-math.cos(r1[2]), abs=1e-3)
    assert math.sin(r2[2]) == pytest.approx(math.sin(r1[2]), abs=1e-3)
    views = {rid: surroundings(grid, p, 4.5) for rid, p in robots.items()}
    assert views["r1"].sum() > 1000    # walls around, not an empty hall
    for rid, view in views.items():
        assert not mismatch(views["r1"], view).any(), f"{rid}'s start looks unlike r1's"
    # while the truth between them is far from the identity their likeness suggests
    assert math.dist(r1[:2], r2[:2]) > 10.0


def test_the_wings_do_not_see_into_each_others_corridors(world: World) -> None:
    from sim.raycast import line_of_sight

    ys = np.linspace(-0.8, 0.8, 5)
    for yc in floorplan.WINGS_CORRIDORS_Y:
        west = [(x, yc + dy) for x in (-14.0, -8.0, -3.0, -1.7) for dy in ys]
        east = [(x, yc + dy) for x in (1.7, 3.0, 8.0, 14.0) for dy in ys]
        seen = [(p, q) for p in west for q in east
                if line_of_sight(p, q, world.segments, world.circles)]
        assert not seen, f"corridor y={yc}: {seen[:3]}"
    # while in the spine itself robots do see each other
    assert line_of_sight((-0.7, -5.0), (0.7, -5.0), world.segments, world.circles)


def test_a_broken_world_file_gives_a_clear_error(tmp_path: object) -> None:
    from pathlib import Path

    bad = Path(str(tmp_path)) / "broken.world"
    bad.write_text(WORLD.read_text()[:2000])
    with pytest.raises(WorldError):
        load_world(bad)
