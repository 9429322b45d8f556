"""Team coordination: spread assignment, and no robot left idle while its team explores."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from server.control import PursuitParams, StuckDetector
from server.exploration import (
    Decision,
    ExplorerParams,
    Finished,
    VisitedTargets,
    VoronoiExplorer,
    assign_optimal,
    assign_spread,
)
from server.exploration.navigator import Navigator
from server.fleet.coordination import (
    Member,
    TeamExplorer,
    in_sight,
    remaining_m,
    walls_beyond_reach,
)
from server.planning import OccupancyGrid
from tests.test_exploration_skeleton import t_corridor


def test_spread_assignment_keeps_goals_apart_while_others_exist() -> None:
    targets = np.array([[0.0, 0.0], [1.0, 0.0], [8.0, 0.0]])
    cost = np.array([[1.0, 2.0, 9.0],
                     [2.0, 1.0, 8.0]])
    assert assign_optimal(cost) == [0, 1]          # 1 m apart: both look into the same space
    # robot 1 giving way costs 9 in all, robot 0 giving way 10
    assert assign_spread(cost, targets, 2.0) == [0, 2]
    assert assign_spread(cost, targets, 0.5) == [0, 1]
    # nothing elsewhere: the robots share rather than one standing idle
    assert assign_spread(cost[:, :2], targets[:2], 2.0) == [0, 1]


@pytest.mark.parametrize("seed", range(8))
def test_spread_assignment_is_the_cheapest_separated_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R, K = 3, 7
    xy = rng.uniform(0, 6, (K, 2))
    cost = rng.uniform(0, 10, (R, K))
    got = assign_spread(cost, xy, 2.0)
    assert None not in got and len(set(got)) == R
    far = lambda a, b: np.hypot(*(xy[a] - xy[b])) >= 2.0  # noqa: E731
    separated = [cols for cols in itertools.permutations(range(K), R)
                 if all(far(a, b) for a, b in itertools.combinations(cols, 2))]
    if separated and all(far(a, b) for a, b in itertools.combinations(got, 2)):
        best = min(sum(cost[r, c] for r, c in enumerate(cols)) for cols in separated)
        total = sum(cost[r, c] for r, c in enumerate(got) if c is not None)
        assert total <= best * 1.5   # greedy giving-way: near the best separated total
    elif separated:
        pytest.fail(f"a separated assignment exists but {got} clashes")


def one_open_end() -> OccupancyGrid:
    """The T corridor with its left end walled off: only the right end leads anywhere."""
    g = t_corridor()
    g.data[29:46, 10] = 100
    return g


def team(mode: str) -> tuple[TeamExplorer, list[Member]]:
    def nav() -> Navigator:
        return Navigator(VoronoiExplorer(ExplorerParams(lam=1.0)), PursuitParams(), None,
                         StuckDetector(), 4.0)

    a = np.array([3.0, 3.75, 0.0])
    b = np.array([4.0, 3.75, 0.0])
    members = [Member("r1", a, a, nav()), Member("r2", b, b, nav())]
    return TeamExplorer(VoronoiExplorer(ExplorerParams(lam=1.0)), "r2", lambda: members,
                        mode, sight_spread=True), members


@pytest.mark.parametrize("mode", ["joint", "greedy"])
def test_a_robot_whose_only_target_is_a_teammates_goes_there_too(mode: str) -> None:
    grid = one_open_end()
    ex, members = team(mode)
    alone = ex.base.decide(grid, members[1].pose, members[1].start_pose, VisitedTargets())
    assert isinstance(alone, Decision) and alone.target_xy[0] > 9.5
    members[0].nav.target_xy = alone.target_xy        # r1 is already on its way there
    reserved = ex.base.decide(grid, members[1].pose, members[1].start_pose, VisitedTargets(),
                              reserved_xy=[alone.target_xy])
    assert isinstance(reserved, Finished)             # nothing else is open ...
    got = ex.decide(grid, members[1].pose, members[1].start_pose, VisitedTargets())
    assert isinstance(got, Decision) and got.target_xy[0] > 9.5   # ... so r2 follows


def test_a_team_with_nothing_open_is_finished() -> None:
    grid = one_open_end()
    grid.data[29:46, 110] = 100                       # both ends walled
    ex, members = team("joint")
    members[0].nav.target_xy = (10.5, 3.75)
    got = ex.decide(grid, members[1].pose, members[1].start_pose, VisitedTargets())
    assert isinstance(got, Finished)


def test_open_space_goes_to_the_long_range_robot_and_the_room_to_the_short_range_one() -> None:
    """A 20 m hall with a 2 × 3 m room in a corner; the two targets cost both robots the same
    drive: the depth camera (3 m) gets the room, the LIDAR (10 m) the middle of the hall."""
    data = np.zeros((200, 200), np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100           # the hall's walls
    data[:30, 20] = data[30, :21] = 100                 # the room's
    grid = OccupancyGrid(data, 0.1, (0.0, 0.0))
    targets = np.array([[10.0, 10.0], [1.0, 1.5]])      # the hall's middle, the room
    extra = walls_beyond_reach(grid, targets, [10.0, 3.0], 2.0)
    assert extra[0].tolist() == [0.0, 0.0]              # the LIDAR sees walls 10 m off
    assert extra[1, 1] == 0.0                           # the room's walls: within 3 m
    assert extra[1, 0] == pytest.approx(2.0 * (9.95 - 3.0), abs=0.1)
    same = np.full((2, 2), 5.0)
    for ranges, want in (([10.0, 3.0], [0, 1]), ([3.0, 10.0], [1, 0])):
        cost = same + walls_beyond_reach(grid, targets, ranges, 2.0)
        assert assign_optimal(cost) == want
    # a team of like sensors, or the weight at 0: nothing changes; the LIDARs differ only
    # by what the longer one sees and the shorter does not
    assert not walls_beyond_reach(grid, targets, [3.0, 3.0], 2.0).any()
    assert walls_beyond_reach(grid, targets, [8.0, 12.0], 2.0)[:, 0].tolist() == \
        pytest.approx([2 * 1.95, 0.0], abs=0.1)
    assert not walls_beyond_reach(grid, targets, [10.0, 3.0], 0.0).any()


def test_in_a_mixed_team_the_long_range_robot_leaves_a_room_in_its_sight_to_the_other() -> None:
    """A room (y > 10 m) above a hall, joined by a door at its east end. Both robots stand
    in the room; two of its targets lie 3 m apart, the third is in the hall behind the wall.
    By path cost both go to the room's targets; in sight of each other within the LIDAR's
    10 m, they clash, and the LIDAR robot, whose giving way costs less, takes the hall."""
    data = np.zeros((200, 200), np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100
    data[100, :170] = 100                               # the wall, a door at x 17-20 m
    grid = OccupancyGrid(data, 0.1, (0.0, 0.0))
    targets = np.array([[8.0, 11.0], [5.0, 12.0], [2.0, 8.0]])   # room, room, hall
    sight = in_sight(grid, targets, 10.0)
    assert sight[0, 1] and sight[1, 0]                  # 3.2 m apart, nothing between
    assert not sight[:2, 2].any()                       # the wall hides the hall's target
    assert not in_sight(grid, targets, 3.0).any()       # beyond a camera's reach
    cost = np.array([[7.0, 10.0, 17.0],                 # the LIDAR robot, at the door
                     [9.0, 8.0, 25.0]])                 # the camera robot, in the room
    assert assign_spread(cost, targets, 2.0) == [0, 1]  # 3 m apart: both in the room
    assert assign_spread(cost, targets, 2.0, sight) == [2, 1]

    ex, members = team("joint")
    members[0].sensor_range_m, members[1].sensor_range_m = 10.0, 3.0
    got = ex._sight_clashes(grid, targets, [10.0, 3.0])
    assert got is not None and (got == sight).all()
    assert ex._sight_clashes(grid, targets, [10.0, 10.0]) is None   # like sensors: as before
    ex.sight_spread = False
    assert ex._sight_clashes(grid, targets, [10.0, 3.0]) is None


def test_the_modes_old_names_still_configure_a_server_and_a_demo(
        caplog: pytest.LogCaptureFixture) -> None:
    """``optimal`` (never optimal) and ``thesis`` (the dissertation's greedy rule) were the
    modes' names before; config files in the wild still say so."""
    from mrslam.demo import DemoConfig
    from server.config import ServerConfig

    for old, new in (("optimal", "joint"), ("thesis", "greedy")):
        assert ServerConfig.model_validate(
            {"teams": {"coordination": old}}).teams.coordination == new
        assert DemoConfig.model_validate({"coordination": old}).coordination == new
        assert f"coordination {old!r} is called {new!r} now" in caplog.text
    assert ServerConfig().teams.coordination == DemoConfig().coordination == "joint"
    with pytest.raises(ValueError, match=r"joint.*greedy"):
        DemoConfig.model_validate({"coordination": "best"})


def long_corridor() -> OccupancyGrid:
    """A 1.5 m wide corridor from x = 1 m to x = 30 m (y 1.5–3.0 m), walled at its west end
    and open onto unknown space at its east end. 10 cm cells."""
    d = np.full((45, 320), -1, np.int8)
    d[15:30, 10:300] = 0
    d[14, 9:300] = d[30, 9:300] = 100
    d[14:31, 9] = 100
    return OccupancyGrid(d, 0.1, (0.0, 0.0))


@pytest.mark.parametrize("r2_x, taken", [(26.0, True), (6.0, False)])
def test_a_goal_is_taken_over_by_a_teammate_that_gets_there_in_less_than_half_the_way(
        r2_x: float, taken: bool) -> None:
    """r1 is 27 m from the corridor's open end, on its way there. r2, deciding, is 3 m
    from it: it takes the goal over and r1 chooses again. From 23 m away (not less than half
    of r1's 27 m) it leaves the goal to r1 and follows it there, as before."""
    grid = long_corridor()
    ex, members = team("joint")
    r1, r2 = members
    r1.pose = np.array([2.0, 2.25, 0.0])
    r2.pose = r2.start_pose = np.array([r2_x, 2.25, 0.0])
    first = ex.base.decide(grid, r1.pose, r1.pose, VisitedTargets())
    assert isinstance(first, Decision) and first.target_xy[0] > 28.0
    r1.nav.redirect(first.target_xy, first.path.xy_m)
    got = ex.decide(grid, r2.pose, r2.start_pose, VisitedTargets())
    assert isinstance(got, Decision) and got.target_xy[0] > 28.0
    assert (r1.nav.target_xy is None) is taken
    assert ex.takeovers == int(taken)
    if not taken:
        assert r1.nav.target_xy == first.target_xy


def test_remaining_path_counts_from_the_nearest_point_on_it() -> None:
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])
    assert remaining_m(path, [4.0, 1.0]) == pytest.approx(1.0 + 6.0 + 5.0)
    assert remaining_m(None, [0.0, 0.0]) == float("inf")
