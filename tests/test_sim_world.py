"""Worlds: the thesis SDF worlds, broken files, nav2 map round trips, the world-map command."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mrslam.cli import app
from mrslam.demo import DemoConfig, plan_run
from sim.errors import WorldError
from sim.grid import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid,
    rasterise,
    read_nav2,
    wall_face_area_m2,
    write_nav2,
)
from sim.loader import load_world
from sim.raycast import RayCaster
from sim.world_map import world_map
from tests.conftest import DATA

THESIS = DATA / "worlds" / "thesis"

BOX_MODEL = """<?xml version='1.0'?>
<sdf version='1.6'><model name='{name}'>
  <pose>{model_pose}</pose>
  <link name='l'><pose>{link_pose}</pose>
    <collision name='c'><pose>0 0 {z} 0 0 0</pose>
      <geometry>{geometry}</geometry></collision></link>
  <static>1</static></model></sdf>
"""


def write_model(models: Path, name: str, geometry: str = "<box><size>2 0.2 2.5</size></box>",
                model_pose: str = "5 5 0 0 0 0", link_pose: str = "0 0 0 0 0 0",
                z: float = 1.25) -> None:
    d = models / name
    d.mkdir(parents=True)
    (d / "model.config").write_text(
        f"<?xml version='1.0'?><model><name>{name}</name><sdf version='1.6'>model.sdf</sdf>"
        "</model>")
    (d / "model.sdf").write_text(BOX_MODEL.format(
        name=name, model_pose=model_pose, link_pose=link_pose, z=z, geometry=geometry))


def write_world(path: Path, includes: list[tuple[str, str | None]]) -> Path:
    inc = "".join(f"<include><uri>model://{n}</uri>"
                  + (f"<pose>{p}</pose>" if p else "") + "</include>" for n, p in includes)
    path.write_text(f"<?xml version='1.0'?><sdf version='1.6'><world name='t'>"
                    f"<include><uri>model://sun</uri></include>"
                    f"<include><uri>model://ground_plane</uri></include>{inc}</world></sdf>")
    return path


@pytest.mark.parametrize("name, size", [("house_small", 20.0), ("house_large", 50.0)])
def test_thesis_worlds_load(name: str, size: float) -> None:
    world = load_world(THESIS / f"{name}.world")
    xmin, ymin, xmax, ymax = world.bounds()
    assert xmax - xmin == pytest.approx(size, abs=0.3)
    assert ymax - ymin == pytest.approx(size, abs=0.3)
    assert len(world.polygons) >= 10 and len(world.segments) == 4 * len(world.polygons)
    # the outer walls are 0.15 m thick boxes: every polygon is a thin rectangle
    widths = [min(np.linalg.norm(p[1] - p[0]), np.linalg.norm(p[2] - p[1]))
              for p in world.polygons]
    assert max(widths) < 0.2


def test_include_pose_replaces_model_pose_and_composes_with_links(tmp_path: Path) -> None:
    models = tmp_path / "models"
    write_model(models, "wall", model_pose="100 100 0 0 0 0", link_pose="1 0 0 0 0 1.5707963")
    world = load_world(write_world(tmp_path / "w.world", [("wall", "2 3 0 0 0 1.5707963")]))
    # include pose (2, 3, 90°) ∘ link (1, 0, 90°): a 2 x 0.2 box centred at (2, 4), along x
    (poly,) = world.polygons
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    assert np.allclose(lo, [1.0, 3.9], atol=1e-6) and np.allclose(hi, [3.0, 4.1], atol=1e-6)
    # without a pose the include keeps the model file's own pose
    world = load_world(write_world(tmp_path / "w2.world", [("wall", None)]))
    assert np.allclose(world.polygons[0].mean(axis=0), [101.0, 100.0], atol=1e-6)


def test_lidar_plane_cuts_boxes_cylinders_and_skips_what_it_misses(tmp_path: Path) -> None:
    models = tmp_path / "models"
    write_model(models, "door", "<box><size>1 0.15 1</size></box>", z=0.5)
    write_model(models, "shelf", "<box><size>1 1 0.5</size></box>", z=0.75)   # 0.5..1.0 m
    write_model(models, "post", "<cylinder><radius>0.3</radius><length>2</length></cylinder>",
                z=1.0)
    write_model(models, "tilted", "<box><size>1 1 1</size></box>", z=0.2,
                link_pose="0 0 0 0.3 0.2 0")
    w = load_world(write_world(tmp_path / "w.world", [
        ("door", "0 0 0 0 0 0"), ("shelf", "5 0 0 0 0 0"), ("post", "0 5 0 0 0 0"),
        ("tilted", "-5 -5 0 0 0 0")]), lidar_height_m=0.2)
    assert len(w.polygons) == 2 and w.circles.tolist() == [[0.0, 5.0, 0.3]]
    assert len(w.polygons[1]) >= 4  # the tilted box cut by z = 0.2 is a convex polygon
    higher = load_world(tmp_path / "w.world", lidar_height_m=1.2)  # above the door now
    assert len(higher.polygons) == 0 and len(higher.circles) == 1


@pytest.mark.parametrize("case, expected", [
    ("mesh", r"model://mesh_model.*|<mesh> geometry is not supported"),
    ("unknown", r"unknown model"),
    ("nocollision", r"no <collision> geometry"),
    ("badpose", r"<pose>1 2 x</pose>"),
    ("xml", r"not valid XML"),
])
def test_broken_worlds_name_file_and_element(tmp_path: Path, case: str, expected: str) -> None:
    models = tmp_path / "models"
    world = tmp_path / "w.world"
    if case == "mesh":
        write_model(models, "mesh_model", "<mesh><uri>model://x/a.dae</uri></mesh>")
        write_world(world, [("mesh_model", None)])
        where = "mesh_model"
    elif case == "unknown":
        write_world(world, [("no_such_model", None)])
        where = "no_such_model"
    elif case == "nocollision":
        d = models / "ghost"
        d.mkdir(parents=True)
        (d / "model.sdf").write_text("<sdf version='1.6'><model name='ghost'><link name='l'>"
                                     "<visual name='v'/></link></model></sdf>")
        write_world(world, [("ghost", None)])
        where = "ghost"
    elif case == "badpose":
        write_model(models, "wall")
        write_world(world, [("wall", "1 2 x")])
        where = "w.world"
    else:
        world.write_text("<sdf><world><include>")
        where = "w.world"
    with pytest.raises(WorldError, match=expected) as err:
        load_world(world)
    assert where in str(err.value) and err.value.user_error
    res = CliRunner().invoke(app, ["world-map", str(world), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2
    assert where in res.output and len(res.output.strip().splitlines()) == 1


def test_nav2_map_round_trip_and_map_world_ray_casting(tmp_path: Path) -> None:
    world = load_world(THESIS / "house_small.world")
    grid = rasterise(world, 0.05)
    write_nav2(grid, tmp_path)
    back = read_nav2(tmp_path / "map.yaml")
    assert back.resolution_m == grid.resolution_m and back.origin == pytest.approx(grid.origin)
    assert np.array_equal(back.cells, grid.cells)  # free, occupied and unknown survive
    img = (tmp_path / "map.pgm").read_bytes()
    assert img.startswith(b"P5")
    # the map as a world: scans agree with the SDF world to within a cell
    mworld = load_world(tmp_path / "map.yaml")
    a, b = RayCaster(world.segments), RayCaster(mworld.segments)
    for pose in [(-8.0, 9.0, 0.0), (0.0, 0.0, 1.0), (5.0, -5.0, -2.0)]:
        ra = a.cast(pose, 400, -math.pi, 2 * math.pi / 400, 10.0)
        rb = b.cast(pose, 400, -math.pi, 2 * math.pi / 400, 10.0)
        both = np.isfinite(ra) & np.isfinite(rb)
        assert (np.isfinite(ra) == np.isfinite(rb)).mean() > 0.97 and both.mean() > 0.5
        assert np.median(np.abs(ra[both] - rb[both])) < 0.05


def test_world_map_free_area_of_the_large_world(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["world-map", str(THESIS / "house_large.world"),
                                   "--resolution", "0.1", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert "free area" in res.output
    grid, fig = world_map(THESIS / "house_large.world", 0.1)
    # enclosed free space: most of the 50 x 50 m box minus walls, never the outside
    assert 2000.0 < fig["free_area_m2"] < 2500.0 < fig["bbox_m2"] + 20.0
    assert fig["largest_region_m2"] > 0.99 * fig["free_area_m2"]
    assert grid.cells[0, 0] == UNKNOWN  # outside the building
    back = read_nav2(tmp_path / "map.yaml")
    assert np.count_nonzero(back.cells == FREE) * 0.01 == pytest.approx(fig["free_area_m2"])
    assert np.count_nonzero(back.cells == OCCUPIED) > 0


def test_wall_face_area_counts_the_walls_as_seen_from_the_free_space() -> None:
    """A 4 m × 3 m room inside 0.3 m walls (cells of 0.1 m): only the walls' inner faces, one
    cell thick, count — not the wall's thickness behind them, not the outside."""
    cells = np.full((40, 50), UNKNOWN, np.int8)      # 5 m × 4 m
    cells[2:38, 2:48] = OCCUPIED                    # walls 0.3 m thick around the room
    cells[5:35, 5:45] = FREE                        # the room: 4 m × 3 m
    grid = OccupancyGrid(cells, 0.1, (0.0, 0.0, 0.0))
    # the ring of cells round the room: (40 + 2) × (30 + 2) − 40 × 30 cells
    assert wall_face_area_m2(grid) == pytest.approx((42 * 32 - 40 * 30) * 0.01)
    cells[20, 5:45] = OCCUPIED                      # a partition: seen from both sides
    assert wall_face_area_m2(grid) == pytest.approx((42 * 32 - 40 * 30 + 40) * 0.01)


def test_default_area_to_cover_adds_the_wall_faces_to_the_free_area() -> None:
    """Coverage counts free and occupied cells as explored, so the demo's default area does
    too: otherwise a threshold is met with part of the free space unseen."""
    _, fig = world_map(THESIS / "house_small.world", 1 / 15)
    assert fig["explorable_area_m2"] == pytest.approx(
        fig["free_area_m2"] + fig["wall_face_area_m2"], abs=1e-3)
    assert 0.0 < fig["wall_face_area_m2"] < fig["occupied_area_m2"]
    plan = plan_run(DemoConfig(scenario="thesis-case-1",
                               scenarios_file=str(THESIS / "scenarios.yaml")))
    assert plan["area_m2"] == pytest.approx(fig["explorable_area_m2"])
