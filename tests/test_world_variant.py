"""A changed building: ``small_house.changed`` (two doors closed, three boxes standing where
the house has open floor), a variant of the small house's site."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import label

from schemas.occupancy import FREE, OCCUPIED
from sim import floorplan
from sim.errors import WorldError
from sim.loader import load_world, site_of
from sim.world_map import world_map

BASE = floorplan.WORLDS_DIR / "small_house.world"
VARIANT = floorplan.WORLDS_DIR / "small_house.changed.world"
RES = 0.05


def _cell(grid, x: float, y: float) -> int:  # type: ignore[no-untyped-def]
    c = int((x - grid.origin[0]) / grid.resolution_m)
    r = int((y - grid.origin[1]) / grid.resolution_m)
    return int(grid.cells[r, c])


def test_the_variant_is_of_the_small_houses_site_and_differs_where_it_should() -> None:
    assert site_of(VARIANT) == site_of(BASE) == "small_house"
    assert load_world(VARIANT).name == "small_house.changed"
    base, _ = world_map(BASE, RES)
    var, _ = world_map(VARIANT, RES)
    assert base.cells.shape == var.cells.shape and np.allclose(base.origin, var.origin)
    changes = [(x, y) for x, y in floorplan.SMALL_HOUSE_CLOSED] + \
        [(b[0], b[1]) for b in floorplan.SMALL_HOUSE_BOXES]
    assert len(changes) == 5
    for x, y in changes:
        assert _cell(base, x, y) == FREE, (x, y)
        assert _cell(var, x, y) == OCCUPIED, (x, y)
    # nothing else differs: every differing cell lies within 0.7 m of a change
    rows, cols = np.nonzero(base.cells != var.cells)
    xs = var.origin[0] + (cols + 0.5) * RES
    ys = var.origin[1] + (rows + 0.5) * RES
    near = np.zeros(len(xs), dtype=bool)
    for x, y in changes:
        near |= np.hypot(xs - x, ys - y) <= 0.7
    assert len(xs) > 0 and near.all()


def test_every_room_of_the_variant_is_still_reached_from_the_scenarios_spawns() -> None:
    var, _ = world_map(VARIANT, RES)
    regions, _ = label(var.cells == FREE)
    # the three robots of small-house-3 stand in one free region, and it is the house
    spawns = [(-8.0, 9.0), (-3.0, 9.0), (4.0, -9.0)]
    ids = {int(regions[int((y - var.origin[1]) / RES), int((x - var.origin[0]) / RES)])
           for x, y in spawns}
    assert len(ids) == 1 and 0 not in ids
    main = regions == ids.pop()
    assert main.sum() >= 0.99 * (var.cells == FREE).sum()


def test_a_broken_variant_is_refused_naming_the_problem(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=r"no door of small_house is centred at \(1\.0, 1\.0\)"):
        floorplan.changed(floorplan.small_house(), "small_house.bad", ((1.0, 1.0),), ())
    with pytest.raises(WorldError, match="must start with its site"):
        site_of(tmp_path / ".changed.world")
    bad = tmp_path / "small_house.broken.world"
    bad.write_text(VARIANT.read_text()[:500])
    with pytest.raises(WorldError, match="not valid XML"):
        load_world(bad)
