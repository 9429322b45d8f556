"""The earliest-sight bound of bench/known_map.py --changed, on the changed small house."""

from __future__ import annotations

from bench.support.earliest import earliest_sight_s
from sim.floorplan import SMALL_HOUSE_BOXES
from tests.conftest import ROOT

CHANGED = ROOT / "sim" / "worlds" / "small_house.changed.world"


def test_a_change_in_view_at_the_start_and_one_rooms_away() -> None:
    north, _, south_east = SMALL_HOUSE_BOXES      # north middle room; south-east room
    changes = [(north[0], north[1], 0.45), (south_east[0], south_east[1], 0.45)]
    starts = {"r1": (-3.0, 5.0, 2.0)}             # in the north middle room, placed at 2 s
    slow = earliest_sight_s(CHANGED, starts, changes, 0.3, 10.0, 0.2)
    fast = earliest_sight_s(CHANGED, starts, changes, 0.6, 10.0, 0.2)
    assert slow[0] == fast[0] == 2.0              # in view where it was placed
    # the south-east room's box: out of the room, along the hall and into the lounge
    assert slow[1] > 2.0 + 8.0 / 0.3
    assert abs((slow[1] - 2.0) - 2 * (fast[1] - 2.0)) < 1e-6
    # a robot placed later sees everything later by as much
    late = earliest_sight_s(CHANGED, {"r1": (-3.0, 5.0, 7.0)}, changes, 0.3, 10.0, 0.2)
    assert late == [t + 5.0 for t in slow]
