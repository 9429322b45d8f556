"""The floor plans of the worlds that ship with mrslam, written out as Gazebo SDF box walls.

The dissertation's figures are kept as facts: a small house of 20 × 20 m and a large one of
50 × 50 m, both centred on the origin, walls 0.15 m thick and 2.5 m high, and the spawn poses of
its four cases, which the house scenarios of ``sim/worlds/scenarios.yaml`` take. The rooms,
doors and corridors are our own, so these are not the dissertation's worlds.
A third world, ``ambiguous_wings`` (30 × 30 m), is ours alone: a self-similar building for
testing that maps are not merged on a look-alike (see docs/ambiguous-world.md). A fourth,
``office_floor`` (30 × 20 m), is a floor of offices on two corridors, where a team must
share out many small rooms (see docs/detours.md).

A plan is a list of straight walls along their centre lines, each with its door openings, and a
few square pillars. ``python -m sim.floorplan`` rewrites ``sim/worlds/*.world`` from this
module; a test checks that the files there are what it writes.
"""

from __future__ import annotations

import itertools
import math
import sys
from dataclasses import dataclass
from pathlib import Path

WALL_THICKNESS_M = 0.15
WALL_HEIGHT_M = 2.5
WORLDS_DIR = Path(__file__).resolve().parent / "worlds"

Point = tuple[float, float]


@dataclass(frozen=True)
class Wall:
    """A straight wall from ``a`` to ``b`` (centre line) with door openings, each
    ``(centre, width)`` in metres along the wall from ``a``."""

    a: Point
    b: Point
    doors: tuple[tuple[float, float], ...] = ()

    @property
    def length_m(self) -> float:
        return math.dist(self.a, self.b)

    def pieces(self, thickness_m: float) -> list[tuple[Point, Point]]:
        """The solid stretches between the doors. The wall's own ends reach ``thickness_m / 2``
        past ``a`` and ``b``, so walls meeting there close the corner; door edges do not, so an
        opening is exactly its width."""
        length = self.length_m
        ux, uy = (self.b[0] - self.a[0]) / length, (self.b[1] - self.a[1]) / length
        cuts = sorted((c - w / 2, c + w / 2) for c, w in self.doors)
        starts = [-thickness_m / 2] + [hi for _, hi in cuts]
        ends = [lo for lo, _ in cuts] + [length + thickness_m / 2]
        return [((self.a[0] + s * ux, self.a[1] + s * uy), (self.a[0] + e * ux, self.a[1] + e * uy))
                for s, e in zip(starts, ends, strict=True) if e - s > 1e-9]


@dataclass(frozen=True)
class Plan:
    name: str
    walls: tuple[Wall, ...]
    pillars: tuple[tuple[float, float, float], ...] = ()   # (x, y, side) [m]
    #: loose boxes standing on the floor: (x, y, yaw [rad], length, width) [m]
    boxes: tuple[tuple[float, float, float, float, float], ...] = ()


def hwall(y: float, x0: float, x1: float, doors: tuple[float, ...] = (),
          width_m: float = 1.0) -> Wall:
    """A wall along ``y`` from ``x0`` to ``x1``, doors centred at the given x."""
    return Wall((x0, y), (x1, y), tuple((abs(x - x0), width_m) for x in doors))


def vwall(x: float, y0: float, y1: float, doors: tuple[float, ...] = (),
          width_m: float = 1.0) -> Wall:
    """A wall along ``x`` from ``y0`` to ``y1``, doors centred at the given y."""
    return Wall((x, y0), (x, y1), tuple((abs(y - y0), width_m) for y in doors))


def small_house() -> Plan:
    """20 × 20 m: three rooms along the north side (the middle one behind a slanted wall),
    a hall along the middle that opens into a lounge in the east, three rooms in the south,
    the south-west corner cut off, a free-standing slanted counter and a short wall in the
    lounge."""
    c = 10.0 - WALL_THICKNESS_M / 2
    return Plan("small_house", (
        # outline, the south-west corner cut at 45°
        hwall(-c, -6.5, c), vwall(c, -c, c), hwall(c, c, -c), vwall(-c, c, -6.5),
        Wall((-c, -6.5), (-6.5, -c)),
        # north rooms: west (r1), middle (r2), east behind a slanted wall
        hwall(3.5, -c, c, doors=(-7.0, -2.0, 5.5)),
        vwall(-5.5, 3.5, c, doors=(6.5,)),
        Wall((0.0, 3.5), (1.5, c), doors=((4.5, 1.0),)),
        # the hall's south side, the south rooms (r3 in the east one) and the lounge
        hwall(1.0, -c, 2.0, doors=(-7.0, -1.0)),
        vwall(-4.0, -c, 1.0, doors=(-5.5,)),
        vwall(2.0, -c, 1.0, doors=(-7.5,)),
        hwall(-3.0, 2.0, c, doors=(7.5,), width_m=1.2),
        Wall((-2.5, -2.5), (0.5, -5.5)),         # a slanted counter, free on both sides
        Wall((c, 0.5), (8.0, 2.0)),              # an alcove in the lounge
    ))


def large_house() -> Plan:
    """50 × 50 m: two 3 m corridors cross at a hall with cut corners and split the house
    into four wings of two to three rooms each; the north-east corner is cut off, two wings
    have a slanted partition, one a partition with a free end and a long room has pillars."""
    c = 25.0 - WALL_THICKNESS_M / 2
    d = 1.2
    return Plan("large_house", (
        # outline, the north-east corner cut at 45°
        hwall(-c, -c, c), vwall(c, -c, 21.0), Wall((c, 21.0), (21.0, c)), hwall(c, 21.0, -c),
        vwall(-c, c, -c),
        # corridors: x = ±1.5 and y = ±1.5, meeting at a hall with slanted corners
        vwall(-1.5, 4.0, c, doors=(19.0, 8.0), width_m=d),
        vwall(1.5, 4.0, c, doors=(20.0, 6.0), width_m=d),
        vwall(-1.5, -c, -4.0, doors=(-18.0, -7.0), width_m=d),
        vwall(1.5, -c, -4.0, doors=(-20.0, -9.0), width_m=d),
        hwall(1.5, -c, -4.0, doors=(-19.0, -8.0), width_m=d),
        hwall(1.5, 4.0, c, doors=(10.0, 20.0), width_m=d),
        hwall(-1.5, -c, -4.0, doors=(-20.0, -9.0), width_m=d),
        hwall(-1.5, 4.0, c, doors=(7.0, 19.0), width_m=d),
        Wall((-1.5, 4.0), (-4.0, 1.5)), Wall((1.5, 4.0), (4.0, 1.5)),
        Wall((-1.5, -4.0), (-4.0, -1.5)), Wall((1.5, -4.0), (4.0, -1.5)),
        # north-west wing: r5 in the outer room, r4 (and large-house-1's robot) beside it
        hwall(13.0, -c, -1.5, doors=(-19.0, -7.0), width_m=d),
        vwall(-13.0, 1.5, c, doors=(7.0, 19.0), width_m=d),
        # north-east wing: r3 in the outer room; a slanted partition, a long room with pillars
        hwall(10.0, 1.5, c, doors=(8.0, 19.0), width_m=d),
        vwall(13.0, 10.0, c, doors=(20.0,), width_m=d),
        Wall((5.0, c), (9.0, 19.0)),
        # south-west wing: r1 in the outer room; a slanted partition in the long room
        hwall(-12.0, -c, -1.5, doors=(-15.0, -5.0), width_m=d),
        vwall(-12.0, -c, -12.0, doors=(-19.0,), width_m=d),
        Wall((-11.0, -12.0), (-7.0, -6.0)),
        # south-east wing: r2 in the outer room; a partition with a free end, a slanted alcove
        vwall(12.0, -c, -1.5, doors=(-20.0, -7.0), width_m=d),
        hwall(-13.0, 12.0, c, doors=(18.0,), width_m=d),
        hwall(-12.0, 1.5, 8.0),
        Wall((c, -5.0), (20.0, -9.0)),
    ), pillars=((8.0, 5.75, 0.5), (17.0, 5.75, 0.5)))


#: the self-similar building: its half size, the spine's half width, the corridors' centre
#: lines (y) and half width, the x of the room partitions and where the rooms' doors are (x)
WINGS_HALF_M = 15.0
WINGS_SPINE_M = 1.5
WINGS_CORRIDORS_Y = (-10.0, 0.0, 10.0)
WINGS_CORRIDOR_HALF_M = 1.0
WINGS_PARTITIONS_X = (6.0, 10.5)
WINGS_DOORS_X = (3.75, 8.25, 12.75)
WINGS_DOOR_M = 1.2
WINGS_SCREEN_HALF_M = 1.5


def mirror_x(wall: Wall) -> Wall:
    """The wall mirrored in the plane x = 0 (its doors stay where they were along it)."""
    return Wall((-wall.a[0], wall.a[1]), (-wall.b[0], wall.b[1]), wall.doors)


def _east_wing() -> tuple[Wall, ...]:
    """One wing of the ambiguous building, east of the spine: three identical corridors
    running east from the spine, each with three identical rooms on either side (doors
    centred), the wing itself symmetric about y = 0."""
    c = WINGS_HALF_M - WALL_THICKNESS_M / 2
    s, h, d = WINGS_SPINE_M, WINGS_CORRIDOR_HALF_M, WINGS_DOOR_M
    walls: list[Wall] = []
    for yc in WINGS_CORRIDORS_Y:
        # the corridor's two sides, a door into each room on either side
        walls += [hwall(yc - h, s, c, doors=WINGS_DOORS_X, width_m=d),
                  hwall(yc + h, s, c, doors=WINGS_DOORS_X, width_m=d)]
    # the rooms between two corridors stand back to back: a wall halfway between them
    for lo, hi in itertools.pairwise(WINGS_CORRIDORS_Y):
        walls.append(hwall((lo + hi) / 2, s, c))
    # the partitions between the rooms of each band, corridor side to corridor side (or to
    # the outline)
    bands = ([(-c, WINGS_CORRIDORS_Y[0] - h)]
             + [(lo + h, hi - h) for lo, hi in itertools.pairwise(WINGS_CORRIDORS_Y)]
             + [(WINGS_CORRIDORS_Y[-1] + h, c)])
    for x in WINGS_PARTITIONS_X:
        walls += [vwall(x, y0, y1) for y0, y1 in bands]
    return tuple(walls)


def ambiguous_wings() -> Plan:
    """30 × 30 m, built to fool map matching: a north-south spine 3 m wide splits the building
    into a west and an east wing, each the mirror image of the other. Each wing has three
    identical corridors 10 m apart, each with three identical rooms at regular spacing on
    either side, and is symmetric about y = 0 itself, so the building looks the same turned
    by half a turn and much the same shifted 10 m north or south. Screens in the spine keep
    robots in one wing from seeing into the other's corridors. Three places break the
    symmetry: a slanted partition with a free end in the east wing's north-east corner room,
    a short wall making a nook in the west wing's middle room north of its south corridor,
    and a pillar off the spine's centre line north of the middle corridors. None of them can
    be seen from the middle or south corridors' middles, where the scenarios start robots."""
    c = WINGS_HALF_M - WALL_THICKNESS_M / 2
    s = WINGS_SPINE_M
    corridor_m = 2 * WINGS_CORRIDOR_HALF_M
    east = _east_wing()
    return Plan("ambiguous_wings", (
        # outline
        hwall(-c, -c, c), vwall(c, -c, c), hwall(c, c, -c), vwall(-c, c, -c),
        # the spine's sides, open where the corridors meet it
        vwall(-s, -c, c, doors=WINGS_CORRIDORS_Y, width_m=corridor_m),
        vwall(s, -c, c, doors=WINGS_CORRIDORS_Y, width_m=corridor_m),
        # a screen on the spine's centre line before each pair of corridor mouths: the wings
        # do not see into each other's corridors (robots meet only in the spine)
        *(vwall(0.0, yc - WINGS_SCREEN_HALF_M, yc + WINGS_SCREEN_HALF_M)
          for yc in WINGS_CORRIDORS_Y),
        *east, *(mirror_x(w) for w in east),
        # what breaks the symmetry
        Wall((11.0, 14.8), (13.5, 12.8)),       # east wing, north-east room: slanted, free end
        hwall(-7.0, -10.5, -8.5),               # west wing, south corridor's middle north room
    ), pillars=((0.7, 5.0, 0.5),))             # the spine, east of its centre line


#: the office floor: its half sizes, the corridors' centre lines (y) and half width, the
#: x of the partitions between offices in the outer rows and in the middle band
OFFICE_HALF_X_M, OFFICE_HALF_Y_M = 15.0, 10.0
OFFICE_CORRIDORS_Y = (-4.0, 4.0)
OFFICE_CORRIDOR_HALF_M = 1.0
OFFICE_LOBBY_X = -12.0
OFFICE_LINK_X = 13.0
OFFICE_OUTER_X = (-12.0, -7.5, -3.0, 1.5, 6.0, 10.5, 15.0)
OFFICE_MIDDLE_X = (-12.0, -7.0, -2.0, 3.0, 8.0, 13.0)


def office_floor() -> Plan:
    """30 × 20 m: a floor of offices on two corridors. Two corridors 2 m wide run east from a
    lobby 3 m wide along the west side; a short link joins their east ends. Offices line
    both: six of 4.5 × 5 m along the outer side of each corridor, five of 5 × 3 m back to
    back in the band between them, each with one door on its corridor."""
    cx, cy = OFFICE_HALF_X_M - WALL_THICKNESS_M / 2, OFFICE_HALF_Y_M - WALL_THICKNESS_M / 2
    (ys, yn), h = OFFICE_CORRIDORS_Y, OFFICE_CORRIDOR_HALF_M
    lobby, link = OFFICE_LOBBY_X, OFFICE_LINK_X
    outer = [(a + b) / 2 for a, b in itertools.pairwise(OFFICE_OUTER_X)]
    middle = [(a + b) / 2 for a, b in itertools.pairwise(OFFICE_MIDDLE_X)]
    walls = [
        hwall(-cy, -cx, cx), vwall(cx, -cy, cy), hwall(cy, cx, -cx), vwall(-cx, cy, -cy),
        # the lobby's east side, open onto both corridors
        vwall(lobby, -cy, cy, doors=OFFICE_CORRIDORS_Y, width_m=2 * h),
        # the corridors' outer sides, a door into each outer office
        hwall(ys - h, lobby, cx, doors=tuple(outer)), hwall(yn + h, lobby, cx, doors=tuple(outer)),
        # their inner sides, a door into each office of the middle band; the band's offices
        # stand back to back, and the link runs past the band's east end
        hwall(ys + h, lobby, link, doors=tuple(middle)),
        hwall(yn - h, lobby, link, doors=tuple(middle)),
        hwall((ys + yn) / 2, lobby, link), vwall(link, ys + h, yn - h),
    ]
    walls += [vwall(x, -cy, ys - h) for x in OFFICE_OUTER_X[1:-1]]
    walls += [vwall(x, yn + h, cy) for x in OFFICE_OUTER_X[1:-1]]
    walls += [vwall(x, y0, y1) for x in OFFICE_MIDDLE_X[1:-1]
              for y0, y1 in ((ys + h, (ys + yn) / 2), ((ys + yn) / 2, yn - h))]
    return Plan("office_floor", tuple(walls))


def changed(plan: Plan, name: str, closed: tuple[Point, ...],
            boxes: tuple[tuple[float, float, float, float, float], ...]) -> Plan:
    """``plan`` as a later visit may find it: the doors centred at the points ``closed``
    shut (the wall run through them) and ``boxes`` standing on the floor. A point that is
    no door's centre (within 5 cm) raises ValueError naming it."""
    walls = list(plan.walls)
    for x, y in closed:
        for i, w in enumerate(walls):
            ux, uy = (w.b[0] - w.a[0]) / w.length_m, (w.b[1] - w.a[1]) / w.length_m
            keep = tuple(d for d in w.doors if math.dist(
                (w.a[0] + d[0] * ux, w.a[1] + d[0] * uy), (x, y)) > 0.05)
            if len(keep) < len(w.doors):
                walls[i] = Wall(w.a, w.b, keep)
                break
        else:
            raise ValueError(f"{name}: no door of {plan.name} is centred at ({x}, {y})")
    return Plan(name, tuple(walls), plan.pillars, plan.boxes + boxes)


#: the small house's changes in ``small_house.changed``: the doors closed (their centres)
#: and the boxes standing where the house has open floor (x, y, yaw, length, width)
SMALL_HOUSE_CLOSED = ((-7.0, 3.5), (-4.0, -5.5))
SMALL_HOUSE_BOXES = ((-3.0, 7.0, 0.0, 0.6, 0.6), (6.0, -0.5, 0.4, 0.8, 0.5),
                     (6.0, -6.5, 0.0, 0.6, 0.6))


def small_house_changed() -> Plan:
    """The small house with two doors closed (the north-west room's from the hall, and the
    one between the two south-west rooms) and three boxes in rooms that had none: the
    same site (a variant: ``<site>.<variant>.world``), for missions on its map."""
    return changed(small_house(), "small_house.changed", SMALL_HOUSE_CLOSED,
                   SMALL_HOUSE_BOXES)


#: the symmetry-breaking features of ``ambiguous_wings``: (what, x, y) of a point on each
AMBIGUOUS_BREAKS = (("slanted partition", 12.25, 13.8), ("nook wall", -9.5, -7.0),
                    ("spine pillar", 0.7, 5.0))

PLANS = {"small_house": small_house, "large_house": large_house,
         "ambiguous_wings": ambiguous_wings, "office_floor": office_floor,
         "small_house.changed": small_house_changed}


def _box(name: str, x: float, y: float, yaw: float, length: float, width: float,
         height: float) -> list[str]:
    pose = f"<pose>{x:.4f} {y:.4f} {height / 2:.4f} 0 0 {yaw:.6f}</pose>"
    geom = f"<geometry><box><size>{length:.4f} {width:.4f} {height:.4f}</size></box></geometry>"
    return [f'        <collision name="{name}">{pose}{geom}</collision>',
            f'        <visual name="{name}">{pose}{geom}</visual>']


def to_sdf(plan: Plan, thickness_m: float = WALL_THICKNESS_M,
           height_m: float = WALL_HEIGHT_M) -> str:
    """The plan as an SDF world: one static model, one box per solid stretch of wall."""
    lines = ['<?xml version="1.0" ?>',
             f"<!-- mrslam's {plan.name.replace('_', ' ')}: written by `python -m "
             "sim.floorplan`; change the plan there -->",
             '<sdf version="1.6">', f'  <world name="{plan.name}">',
             "    <include><uri>model://sun</uri></include>",
             "    <include><uri>model://ground_plane</uri></include>",
             f'    <model name="{plan.name}">', "      <static>true</static>",
             '      <link name="walls">']
    k = 0
    for wall in plan.walls:
        for (x0, y0), (x1, y1) in wall.pieces(thickness_m):
            lines += _box(f"wall_{k}", (x0 + x1) / 2, (y0 + y1) / 2,
                          math.atan2(y1 - y0, x1 - x0), math.dist((x0, y0), (x1, y1)),
                          thickness_m, height_m)
            k += 1
    for i, (x, y, side) in enumerate(plan.pillars):
        lines += _box(f"pillar_{i}", x, y, 0.0, side, side, height_m)
    for i, (x, y, yaw, length, width) in enumerate(plan.boxes):
        lines += _box(f"box_{i}", x, y, yaw, length, width, 1.0)
    lines += ["      </link>", "    </model>", "  </world>", "</sdf>", ""]
    return "\n".join(lines)


def write_worlds(folder: Path = WORLDS_DIR) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for name, make in PLANS.items():
        path = folder / f"{name}.world"
        path.write_text(to_sdf(make()))
        out.append(path)
    return out


if __name__ == "__main__":
    for p in write_worlds(Path(sys.argv[1]) if len(sys.argv) > 1 else WORLDS_DIR):
        print(p)
