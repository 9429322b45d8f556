"""The pass over a known map: what is left to see again, and where each robot is sent."""

from __future__ import annotations

import numpy as np

from server.knownmap.sweep import CELL_M, MIN_GAIN, Sweep
from server.knownmap.views import BINS


def _wall(x: float, y0: float, y1: float) -> np.ndarray:
    ys = np.arange(y0, y1, CELL_M / 2)
    return np.column_stack([np.full(len(ys), x), ys])


#: two older views: one near (x = 1) sees a short wall, one far (x = 10) a long one
HITS = {("g", 0): _wall(2.0, -1.0, 1.0), ("g", 1): _wall(12.0, -4.0, 4.0)}
OWNERS = list(HITS)
XY = np.array([[1.0, 0.0], [10.0, 0.0]])


def hits(gid: str, i: int) -> np.ndarray:
    return HITS[(gid, i)]


def _started() -> Sweep:
    s = Sweep()
    s.start(OWNERS, hits)
    return s


def test_cells_are_seen_again_by_beams_that_reach_them() -> None:
    s = _started()
    total = s.total
    assert total > 2 * MIN_GAIN
    # beams of 1 m: nothing reached
    s.saw(np.full(BINS, 1.0), np.array([0.0, 0.0, 0.0]))
    assert s.share_seen() == 0.0
    # from (0, 0), beams reaching 3 m: the near wall (x = 2) is seen again, the far one not
    s.saw(np.full(BINS, 3.0), np.array([0.0, 0.0, 0.0]))
    assert s.todo is not None and 0.0 < s.share_seen() < 1.0
    assert all(c[0] * CELL_M >= 11.0 for c in s.todo)


def test_a_robot_goes_where_most_is_left_per_metre_and_two_robots_split() -> None:
    s = _started()
    pose = np.array([0.0, 0.0, 0.0])
    # the far view shows four times as much: worth the way there
    assert s.goal("r1", pose, OWNERS, XY, hits) == (10.0, 0.0)
    # a second robot is not sent to what the first will see: the near place is left
    assert s.goal("r2", pose, OWNERS, XY, hits) == (1.0, 0.0)
    # once what r1's place shows has been seen on the way, r1 is sent on; nothing is left
    assert not s.stale("r1", hits)
    s.saw(np.full(BINS, 5.0), np.array([8.0, 0.0, 0.0]))
    assert s.stale("r1", hits)
    assert s.goal("r1", np.array([8.0, 0.0, 0.0]), OWNERS, XY, hits) is None


def test_a_return_near_a_wall_the_map_shows_is_no_new_wall() -> None:
    """An earlier mission's wall drawn some centimetres off: returns on the true wall, near
    it, are not taken for a new wall; returns well out on the open floor are."""
    from scipy.ndimage import binary_dilation

    from server.knownmap.changes import WALL_GAP_M, Upkeep
    from server.knownmap.config import KnownMapConfig
    from server.rendezvous.mapmatch import Layers

    fine_m, n = 0.05, 60
    occ = np.zeros((n, n), dtype=bool)
    occ[30, :] = True                                   # a wall along a row
    free = ~occ
    clear = free & ~binary_dilation(occ, iterations=2)
    lay = Layers(np.zeros(2), 0.2, occ[::4, ::4], free[::4, ::4], np.zeros(2), fine_m,
                 occ, free, binary_dilation(occ), clear)
    u = Upkeep(KnownMapConfig())
    open_ = u._open(lay)
    off = 30 + round(0.15 / fine_m)                # 0.15 m from the wall drawn
    far = 30 + round((WALL_GAP_M + 0.1) / fine_m)
    assert clear[off, 10] and not open_[off, 10]
    assert open_[far, 10] and not open_[30, 10]
    assert u._open(lay) is open_                        # kept for the same layers


def _open_floor() -> object:
    """A map 3 × 3 m of open floor with a wall along one row (y = 1.5 m)."""
    from scipy.ndimage import binary_dilation

    from server.rendezvous.mapmatch import Layers

    fine_m, n = 0.05, 60
    occ = np.zeros((n, n), dtype=bool)
    occ[30, :] = True
    free = ~occ
    clear = free & ~binary_dilation(occ, iterations=2)
    return Layers(np.zeros(2), 0.2, occ[::4, ::4], free[::4, ::4], np.zeros(2), fine_m,
                  occ, free, binary_dilation(occ), clear)


def _views(poses: list[tuple[float, float, float]], bodies: np.ndarray | None = None
           ) -> int:
    """A box (returns around (1.0, 0.5), open floor on the map) seen by keyframes at
    ``poses`` (x, y, s): how many of its cells end confirmed changed."""
    from types import SimpleNamespace
    from typing import Any, cast

    from server.knownmap.changes import Old, Upkeep
    from server.knownmap.config import KnownMapConfig

    u = Upkeep(KnownMapConfig())
    lay = cast(Any, _open_floor())
    box = np.array([[1.0 + dx, 0.5 + dy] for dx in np.arange(-0.1, 0.11, 0.05)
                    for dy in (-0.1, 0.1)])
    old = Old([], np.zeros((0, 3)))
    for x, y, s in poses:
        T = np.array([x, y, 0.0])
        kf = SimpleNamespace(hits=box - T[:2], stamp_ns=int(s * 1e9))
        u._vote(cast(Any, None), cast(Any, kf), T, np.full(BINS, np.nan), old, lay,
                bodies)
    return len(u.changed_xy("wall", 0.05))


def test_a_change_needs_two_views_apart_in_time_and_place() -> None:
    """Returns on the map's open floor are a change once seen by keyframes 4 s and 1 m
    apart; seen longer from one place (a robot standing, watching a person stand) they
    are not."""
    from server.knownmap.changes import CHANGE_SPAN_S, VIEWS_APART_M

    assert _views([(0.2, 0.2, 0.0), (0.2, 1.2, CHANGE_SPAN_S + 1)]) > 0
    assert _views([(0.2, 0.2, 0.0), (0.2, 0.3, CHANGE_SPAN_S + 5)]) == 0     # one place
    assert _views([(0.2, 0.2, 0.0), (0.2, 0.2 + VIEWS_APART_M + 0.1, 1.0)]) == 0  # 1 s
    assert _views([(0.2, 0.2, 0.0), (0.2, 0.3, 6.0), (0.2, 1.4, 9.0)]) > 0


def test_returns_on_a_robot_of_the_team_are_never_a_change() -> None:
    """The same returns, where a robot of the team stands (its footprint), get no vote."""
    views = [(0.2, 0.2, 0.0), (0.2, 1.2, 5.0), (2.5, 0.2, 10.0)]
    assert _views(views) > 0
    robot = np.array([[1.0, 0.5, 0.13 + 0.15]])
    assert _views(views, robot) == 0
    elsewhere = np.array([[2.5, 2.5, 0.28]])
    assert _views(views, elsewhere) > 0


def test_a_place_given_to_see_a_change_again_is_the_nearest_and_given_once() -> None:
    """``urgent`` places (those that see a change seen once): the nearest not given yet,
    whatever it shows, kept until it is reached or no longer needed; none left: None."""
    from server.knownmap.sweep import URGENT

    s = _started()
    pose = np.array([9.0, 0.0, 0.0])
    assert s.goal("r1", pose, OWNERS, XY, hits, urgent=[0, 1]) == (10.0, 0.0)
    assert s.goals["r1"][2] == URGENT and not s.stale("r1", hits)
    assert s.goal("r2", pose, OWNERS, XY, hits, urgent=[1]) is None       # given already
    assert s.goal("r2", pose, OWNERS, XY, hits, urgent=[0, 1]) == (1.0, 0.0)


def test_a_change_seen_once_keeps_the_pass_going_until_seen_again() -> None:
    """A box seen by one keyframe only is no change yet; the older keyframe whose beams
    crossed that floor, 1 m or more from where it was seen, is where to see it again — and
    once a second view has confirmed it, nowhere is."""
    from types import SimpleNamespace
    from typing import Any, cast

    from server.knownmap.changes import CHANGE_SPAN_S, Old, Upkeep
    from server.knownmap.config import KnownMapConfig

    u = Upkeep(KnownMapConfig())
    lay = cast(Any, _open_floor())
    box = np.array([[1.0 + dx, 0.5 + dy] for dx in np.arange(-0.1, 0.11, 0.05)
                    for dy in (-0.1, 0.1)])
    # two older keyframes: one at (2.5, 0.5) whose beams crossed the floor where the box now
    # stands, one at (2.5, 2.5) beyond the wall (beams of 0.5 m: it saw nothing of it)
    profs = {("g", 0): np.full(BINS, 3.0), ("g", 1): np.full(BINS, 0.5)}
    old = Old(list(profs), np.array([[2.5, 0.5, 0.0], [2.5, 2.5, 0.0]]))
    u._cache = {k: (np.zeros((0, 2)), p) for k, p in profs.items()}
    fleet = cast(Any, None)

    def view(x: float, y: float, s: float) -> None:
        T = np.array([x, y, 0.0])
        kf = SimpleNamespace(hits=box - T[:2], stamp_ns=int(s * 1e9))
        u._vote(fleet, cast(Any, kf), T, np.full(BINS, np.nan), Old([], np.zeros((0, 3))),
                lay)

    assert u._confirming(fleet, old) == []              # nothing seen yet
    view(0.2, 0.2, 0.0)
    assert len(u._unconfirmed()[0]) > 0
    assert u._confirming(fleet, old) == [0]
    # a place within 1 m of where it was first seen is no second view
    near = Old(list(profs), np.array([[0.4, 0.2, 0.0], [2.5, 2.5, 0.0]]))
    assert u._confirming(fleet, near) == []
    view(0.2, 1.2, CHANGE_SPAN_S + 1)                    # the second view confirms it
    assert len(u.changed_xy("wall", 0.05)) > 0
    assert u._confirming(fleet, old) == []
