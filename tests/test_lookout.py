"""Looking at what moves: a compact group of returns in known free space turns the robot."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from schemas.se2 import wrap_angle
from server.lookout import Lookout, LookParams, moving_object
from server.planning import OccupancyGrid


def free_room() -> OccupancyGrid:
    data = np.zeros((200, 200), dtype=np.int8)       # 10 × 10 m, 5 cm cells, all free
    data[:, :3] = data[:, -3:] = data[:3, :] = data[-3:, :] = 100
    return OccupancyGrid(data, 0.05, (-5.0, -5.0))


def blob(x: float, y: float, n: int = 6) -> np.ndarray:
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    return np.stack([x + 0.13 * np.cos(a), y + 0.13 * np.sin(a)], axis=1)


def walls_seen(pose: np.ndarray) -> np.ndarray:
    """Returns on the room's walls, in the robot frame."""
    xs = np.linspace(-4.8, 4.8, 60)
    world = np.concatenate([np.stack([xs, np.full(60, 4.9)], 1),
                            np.stack([np.full(60, 4.9), xs], 1)])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return (world - pose[:2]) @ np.array([[c, -s], [s, c]])


def test_a_robot_in_free_space_is_found_and_walls_are_not() -> None:
    pose = np.array([0.0, 0.0, 0.0])
    g, p = free_room(), LookParams()
    assert moving_object(walls_seen(pose), pose, g, np.zeros((0, 2)), p) is None
    pts = np.concatenate([walls_seen(pose), blob(0.0, 2.0)])
    b = moving_object(pts, pose, g, np.zeros((0, 2)), p)
    assert b is not None and abs(b - math.pi / 2) < 0.05
    # a teammate where the blob is: known, not a stranger
    assert moving_object(pts, pose, g, np.array([[0.0, 2.0]]), p) is None
    # too far to read a tag
    assert moving_object(np.concatenate([walls_seen(pose), blob(0.0, 4.2)]), pose, g,
                         np.zeros((0, 2)), p) is None


def test_lookout_turns_holds_then_cools_down() -> None:
    look = Lookout(LookParams(hold_s=1.0, cooldown_s=10.0, approach_range_m=0.0))
    g = free_room()
    pose = np.array([0.0, 0.0, 0.0])
    pts = np.concatenate([walls_seen(pose), blob(-2.0, 0.0)])    # behind the robot
    t = 0.0
    tw = look.step(t, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and abs(tw.omega_rps) > 0
    while tw is not None and tw.omega_rps != 0.0 and t < 10:
        pose = np.add(pose, [0.0, 0.0, 0.1 * tw.omega_rps])
        t += 0.1
        tw = look.step(t, pose, pts, g, np.zeros((0, 2)))
    assert abs(wrap_angle(pose[2] - math.pi)) < math.radians(8)
    assert tw is not None and tw.omega_rps == 0.0 and tw.v_mps == 0.0    # holding
    assert look.step(t + 1.1, pose, pts, g, np.zeros((0, 2))) is None     # done
    # the same thing right after: no new look during the cooldown
    assert look.step(t + 2.0, np.array([0.0, 0.0, 0.0]), pts, g, np.zeros((0, 2))) is None
    assert look.looks == 1
    # already in view: nothing to do
    ahead = np.concatenate([walls_seen(np.zeros(3)), blob(2.0, 0.1)])
    assert Lookout(LookParams(approach_range_m=0.0)).step(0.0, np.zeros(3), ahead, g,
                                                          np.zeros((0, 2))) is None


def to_robot(pose: np.ndarray, world: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return (world - pose[:2]) @ np.array([[c, -s], [s, c]])


def test_a_far_mover_is_approached_until_its_tag_can_be_read() -> None:
    p = LookParams(approach_range_m=8.0, approach_confirm=3, approach_stop_m=1.2)
    look, g = Lookout(p), free_room()
    other = np.array([2.5, 0.0])
    pose = np.array([-3.5, 0.0, math.pi / 2])           # 6 m away, the mover on its right
    t, twists = 0.0, []
    for _ in range(600):
        pts = np.concatenate([walls_seen(pose), to_robot(pose, blob(*other))])
        tw = look.step(t, pose, pts, g, np.zeros((0, 2)))
        twists.append(tw)
        if tw is None and len(twists) > 3:
            break
        if tw is not None:
            pose = pose + 0.1 * np.array([tw.v_mps * math.cos(pose[2]),
                                          tw.v_mps * math.sin(pose[2]), tw.omega_rps])
        t += 0.1
    assert twists[0] is None and twists[1] is None       # not yet seen in 3 scans in a row
    assert twists[2] is not None
    assert any(tw is not None and tw.v_mps > 0 for tw in twists)   # it drove toward it
    assert look.approaches == 1 and look.looks == 1 and look.moved
    d = math.hypot(*(other - pose[:2]))
    assert 0.6 < d <= 1.3                                 # close enough to read its heading
    bearing = wrap_angle(math.atan2(other[1] - pose[1], other[0] - pose[0]) - pose[2])
    assert abs(bearing) < math.radians(10)               # and facing it


def test_an_approach_gives_up_when_the_mover_is_lost() -> None:
    p = LookParams(approach_range_m=8.0, approach_confirm=2, lost_s=1.0, cooldown_s=10.0)
    look, g = Lookout(p), free_room()
    pose = np.array([-3.5, 0.0, 0.0])
    seen = np.concatenate([walls_seen(pose), to_robot(pose, blob(2.5, 0.0))])
    look.step(0.0, pose, seen, g, np.zeros((0, 2)))
    tw = look.step(0.1, pose, seen, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps > 0 and look.active
    empty = walls_seen(pose)
    assert look.step(0.5, pose, empty, g, np.zeros((0, 2))) is not None   # still going
    assert look.step(1.2, pose, empty, g, np.zeros((0, 2))) is None       # lost: given up
    assert not look.active
    assert look.step(2.0, pose, seen, g, np.zeros((0, 2))) is None        # cooling down
    # a far group that is a teammate is never approached
    mates = Lookout(p)
    for k in range(5):
        assert mates.step(0.1 * k, pose, seen, g, np.array([[2.5, 0.0]])) is None


def test_a_mover_in_reading_range_but_not_close_is_approached() -> None:
    look, g = Lookout(LookParams(approach_stop_m=1.2)), free_room()
    pose = np.zeros(3)
    pts = np.concatenate([walls_seen(pose), blob(3.0, 0.2)])       # 3 m ahead, in view
    tw = look.step(0.0, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps > 0 and look.approaching
    close = np.concatenate([walls_seen(pose), blob(1.0, 0.05)])    # already close, in view
    assert Lookout(LookParams(approach_stop_m=1.2)).step(0.0, pose, close, g,
                                                         np.zeros((0, 2))) is None


def test_a_followed_mover_that_got_mapped_as_obstacle_is_still_tracked() -> None:
    p = LookParams(approach_range_m=8.0, approach_confirm=2, lost_s=0.5)
    look, g = Lookout(p), free_room()
    pose = np.array([-3.5, 0.0, 0.0])
    seen = np.concatenate([walls_seen(pose), to_robot(pose, blob(2.5, 0.0))])
    look.step(0.0, pose, seen, g, np.zeros((0, 2)))
    assert look.step(0.1, pose, seen, g, np.zeros((0, 2))) is not None and look.approaching
    g.data[95:106, 145:156] = 100         # it stood still: the map now has it as an obstacle
    for k in range(2, 12):
        tw = look.step(0.1 * k, pose, seen, g, np.zeros((0, 2)))
        assert tw is not None and tw.v_mps > 0         # still going for it


def test_a_sure_call_is_driven_to_even_where_the_lidar_shows_nothing(
        caplog: pytest.LogCaptureFixture) -> None:
    """The reader of a far tag knows where the other robot is: it goes there."""
    look, g = Lookout(LookParams(approach_range_m=10.0, lost_s=1.0), "r7"), free_room()
    pose = np.array([-4.0, 0.0, math.pi])                 # facing away; nothing moves in view
    look.hear(0.0, np.array([3.0, 0.0]), 0.7, sure=True)
    with caplog.at_level(logging.INFO, logger="server.lookout"):
        tw = look.step(0.05, pose, walls_seen(pose), g, np.zeros((0, 2)))
    assert tw is not None and look.approaching and look.calls == 1
    assert "r7: answering a call from 7.0 m away (sure)" in caplog.text  # names the robot
    assert tw.omega_rps != 0.0                            # turning toward the call
    # further sightings keep the approach alive with no LIDAR support at all
    for k in range(1, 30):
        look.hear(0.1 * k, np.array([3.0, 0.0]), 0.7, sure=True)
        assert look.step(0.1 * k + 0.05, pose, walls_seen(pose), g, np.zeros((0, 2))) is not None
    # sightings stop: lost after lost_s
    assert look.step(4.5, pose, walls_seen(pose), g, np.zeros((0, 2))) is None
    assert not look.active


def test_an_unsure_call_follows_the_nearest_mover_or_turns_to_find_the_reader() -> None:
    """The robot that was seen only roughly knows where the reader is: it takes the moving
    thing nearest the estimate; with none in tolerance, it turns once on the spot until it
    reads the reader's tag (a sure call), then goes there."""
    g = free_room()
    pose = np.array([-3.5, 0.0, math.pi / 2])
    reader = np.array([2.5, 0.5])
    pts = np.concatenate([walls_seen(pose), to_robot(pose, blob(*reader))])
    look = Lookout(LookParams(approach_range_m=10.0))
    look.hear(0.0, np.array([2.0, -1.0]), 2.0, sure=False)   # 1.6 m off, within tolerance
    tw = look.step(0.05, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and look.approaching
    assert look.track is not None and math.hypot(*(look.track - reader)) < 0.3
    # estimate far off any mover: turn on the spot, without driving
    p = LookParams(approach_range_m=10.0, max_range_m=2.0, omega_rps=1.0, cooldown_s=10.0)
    look = Lookout(p)
    look.hear(0.0, np.array([-3.5, -3.0]), 1.0, sure=False)
    tw = look.step(0.05, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and tw.omega_rps > 0 and look.active
    assert not look.approaching and look.spin_until_s is not None
    tw = look.step(3.0, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and tw.omega_rps > 0      # still turning
    # the reader's tag came into view: now it knows where the reader is and goes
    look.hear(3.1, reader, 0.5, sure=True)
    tw = look.step(3.15, pose, pts, g, np.zeros((0, 2)))
    assert tw is not None and look.approaching and look.spin_until_s is None
    # a full turn without seeing anyone ends the search
    look = Lookout(p)
    look.hear(0.0, np.array([-3.5, -3.0]), 1.0, sure=False)
    look.step(0.05, pose, walls_seen(pose), g, np.zeros((0, 2)))
    assert look.step(6.5, pose, walls_seen(pose), g, np.zeros((0, 2))) is None
    assert not look.active
    # a stale call is ignored
    look = Lookout(LookParams(approach_range_m=10.0, lost_s=1.0))
    look.hear(0.0, np.array([2.0, -1.0]), 2.0, sure=False)
    assert look.step(3.0, pose, walls_seen(pose), g, np.zeros((0, 2))) is None


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_the_search_for_a_reader_turns_toward_the_rough_place_first(side: float) -> None:
    """The call's place is rough, but it says on which side the reader is: the robot turns
    that way (the shorter way round to it), and keeps that way until it reads the tag."""
    g = free_room()
    pose = np.array([-3.5, 0.0, 0.0])
    p = LookParams(approach_range_m=10.0, max_range_m=2.0, omega_rps=1.0, cooldown_s=10.0)
    look = Lookout(p)
    look.hear(0.0, np.array([-1.0, side * 4.0]), 1.0, sure=False)   # 58° to one side
    tw = look.step(0.05, pose, walls_seen(pose), g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and look.spin_until_s is not None
    assert math.copysign(1.0, tw.omega_rps) == side
    tw = look.step(2.0, pose, walls_seen(pose), g, np.zeros((0, 2)))
    assert tw is not None and math.copysign(1.0, tw.omega_rps) == side   # still that way


def test_a_call_from_close_by_cuts_an_approach_short_and_holds_to_meet() -> None:
    p = LookParams(approach_range_m=10.0, approach_confirm=2, max_range_m=2.0, hold_s=1.0,
                   meet_hold_s=3.0)
    look, g = Lookout(p), free_room()
    pose = np.array([-3.5, 0.0, 0.0])
    far = np.concatenate([walls_seen(pose), to_robot(pose, blob(3.0, 0.0))])
    look.step(0.0, pose, far, g, np.zeros((0, 2)))
    assert look.step(0.1, pose, far, g, np.zeros((0, 2))) is not None and look.approaching
    # a robot of another team read our tag from 1.3 m, behind us: face it and hold
    look.hear(0.2, np.array([-4.8, 0.0]), 1.0, sure=False)
    tw = look.step(0.25, pose, far, g, np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and not look.approaching and look.calls == 1
    t = 0.25
    while tw is not None and tw.omega_rps != 0.0 and t < 10:
        pose = np.add(pose, [0.0, 0.0, 0.1 * tw.omega_rps])
        t += 0.1
        tw = look.step(t, pose, far, g, np.zeros((0, 2)))
    assert abs(wrap_angle(pose[2] - math.pi)) < math.radians(8)
    # further calls while meeting change nothing; the hold lasts meet_hold_s, not hold_s
    look.hear(t + 1.0, np.array([-4.8, 0.0]), 1.0, sure=False)
    held = look.step(t + 2.0, pose, far, g, np.zeros((0, 2)))
    assert held is not None and held.v_mps == 0.0 and held.omega_rps == 0.0
    assert look.calls == 1
    assert look.step(t + 3.2, pose, far, g, np.zeros((0, 2))) is None     # done, cooling down
    # a call heard during the cooldown is not taken up
    look.hear(t + 4.0, np.array([-4.8, 0.0]), 1.0, sure=False)
    assert look.step(t + 4.1, pose, far, g, np.zeros((0, 2))) is None


def test_a_close_call_is_taken_up_during_the_cooldown_of_an_ordinary_look() -> None:
    look = Lookout(LookParams(hold_s=0.5, cooldown_s=15.0, approach_range_m=0.0,
                              max_range_m=2.0))
    look.next_s = 10.0                       # an ordinary look ended a moment ago
    pose = np.zeros(3)
    assert look.step(1.0, pose, walls_seen(pose), free_room(), np.zeros((0, 2))) is None
    look.hear(1.0, np.array([0.0, 1.3]), 1.0, sure=False)    # someone 1.3 m to the left
    tw = look.step(1.05, pose, walls_seen(pose), free_room(), np.zeros((0, 2)))
    assert tw is not None and tw.v_mps == 0.0 and tw.omega_rps > 0


def test_an_unsure_call_with_the_readers_distance_faces_what_stands_there() -> None:
    """The tag's heading put the reader 3 m off (outside the call's tolerance), and another
    moving thing lies nearer that wrong place: the thing standing free at the reader's
    distance, which the reader measured, is the reader, and the robot turns to face it."""
    g = free_room()
    pose = np.array([-3.5, 0.0, math.pi / 2])
    reader, decoy = np.array([2.5, 0.5]), np.array([-1.0, -3.5])
    pts = np.concatenate([walls_seen(pose), to_robot(pose, blob(*reader)),
                          to_robot(pose, blob(*decoy))])
    wrong = np.array([0.5, -3.5])                       # 3 m from the reader, 1.5 from the decoy
    dist = math.hypot(*(reader - pose[:2]))
    look = Lookout(LookParams(approach_range_m=10.0))
    look.hear(0.0, wrong, 2.0, sure=False, range_m=dist, range_tolerance_m=0.3)
    tw = look.step(0.05, pose, pts, g, np.zeros((0, 2)))
    toward = math.atan2(reader[1] - pose[1], reader[0] - pose[0])
    assert look.heading is not None and abs(wrap_angle(look.heading - toward)) < 0.05
    assert look.meeting and not look.approaching and look.spin_until_s is None
    assert tw is not None and tw.v_mps == 0.0 and tw.omega_rps < 0      # turning right
    # facing it, the robot reads the reader's tag: a sure call, and it goes closer
    look.hear(0.5, reader, 0.6, sure=True)
    tw = look.step(0.55, pose, pts, g, np.zeros((0, 2)))
    assert look.approaching and look.track is not None
    assert math.hypot(*(look.track - reader)) < 0.3
    # without the distance, the decoy nearest the wrong place is taken
    look = Lookout(LookParams(approach_range_m=10.0))
    look.hear(0.0, wrong, 2.0, sure=False)
    look.step(0.05, pose, pts, g, np.zeros((0, 2)))
    assert look.track is not None and math.hypot(*(look.track - decoy)) < 0.3
    # nothing standing free at that distance (only the room's walls): as before
    wall_dist = 4.9 - pose[0]
    look = Lookout(LookParams(approach_range_m=10.0))
    look.hear(0.0, wrong, 2.0, sure=False, range_m=wall_dist, range_tolerance_m=0.3)
    look.step(0.05, pose, pts, g, np.zeros((0, 2)))
    assert look.track is not None and math.hypot(*(look.track - decoy)) < 0.3


def test_things_standing_free_at_a_distance_are_found_where_the_map_does_not_reach() -> None:
    """A robot read through a door stands where this robot has no map yet: it is still
    found, by the LIDAR seeing past it on both sides; a wall crossing that distance is not."""
    from server.lookout import objects_at_range

    pose = np.array([0.0, 0.0, 0.0])
    a = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    r = np.full(360, 9.0)                                # far walls all round
    pts = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    body = blob(6.0, 2.0)
    near_side = body[np.hypot(*body.T) < math.hypot(6.0, 2.0)]
    bearing = np.arctan2(near_side[:, 1], near_side[:, 0])
    keep = np.all(np.abs(np.subtract.outer(a, bearing)) > math.radians(1.0), axis=1)
    pts = np.concatenate([pts[keep], near_side])       # the body hides the wall behind it
    unknown = OccupancyGrid(np.full((400, 400), -1, dtype=np.int8), 0.05, (-10.0, -10.0))
    found = objects_at_range(pts, pose, unknown, math.hypot(6.0, 2.0), 0.3)
    assert len(found) == 1 and math.hypot(*(found[0] - [6.0, 2.0])) < 0.2
    assert objects_at_range(pts, pose, unknown, 9.0, 0.3) == []   # the walls: too wide
    assert objects_at_range(pts, pose, None, 4.0, 0.3) == []


def test_a_rough_call_with_nobody_at_the_readers_distance_is_not_answered() -> None:
    """A LIDAR that sees past the reader's distance all round, and nothing standing there:
    no robot read this one's tag from there (a tag misread, or read where no robot stood),
    so the robot neither turns on the spot nor follows the nearest mover. A sensor that
    sees less far than that distance (a depth camera's 3 m) still turns to find the
    reader."""
    g = free_room()
    pose = np.array([-3.5, 0.0, math.pi / 2])
    decoy = np.array([-1.0, -3.5])
    pts = np.concatenate([walls_seen(pose), to_robot(pose, blob(*decoy))])
    rough = np.array([0.5, -3.5])               # 1.5 m from the decoy, within tolerance
    # a LIDAR of 10 m: the call leads nowhere; the robot goes on with what it did
    look = Lookout(LookParams(approach_range_m=10.0, omega_rps=1.0))
    look.sensor_range_m = 10.0
    look.hear(0.0, rough, 2.0, sure=False, range_m=5.4, range_tolerance_m=0.3)
    assert look.step(0.05, pose, pts, g, np.zeros((0, 2))) is None
    assert not look.active and look.track is None and look.calls_unseen == 1
    # a depth camera's 3 m: it could not have seen the reader, so it looks for it
    look = Lookout(LookParams(approach_range_m=10.0, omega_rps=1.0))
    look.sensor_range_m = 3.0
    pts_near = walls_seen(pose)[np.hypot(*walls_seen(pose).T) < 3.0]
    look.hear(0.0, np.array([-3.5, -4.0]), 1.0, sure=False, range_m=5.4,
              range_tolerance_m=0.3)
    tw = look.step(0.05, pose, pts_near, g, np.zeros((0, 2)))
    assert tw is not None and look.active and look.calls == 1
    assert look.calls_unseen == 0


def test_only_a_scan_all_round_tells_how_far_nobody_stands() -> None:
    """The lookout is told the robot's sensor range only when its latest scan spans all
    round: a 360° LIDAR's; not a 270° one's (a reader in its blind sector), nor a depth
    camera's, nor before any scan."""
    from types import SimpleNamespace

    from server.command.steering import sight_range_m

    def robot(span_deg: float | None, range_m: float = 12.0) -> object:
        view = None if span_deg is None else SimpleNamespace(
            angles=np.radians(np.arange(0.0, span_deg, 1.0) - span_deg / 2))
        return SimpleNamespace(view=view, sensor_range_m=range_m)

    assert sight_range_m(robot(360.0)) == 12.0            # type: ignore[arg-type]
    assert sight_range_m(robot(270.0)) == 0.0             # type: ignore[arg-type]
    assert sight_range_m(robot(60.0, 3.0)) == 0.0         # type: ignore[arg-type]
    assert sight_range_m(robot(None)) == 0.0              # type: ignore[arg-type]


def test_a_rough_call_from_within_tag_range_is_answered_even_with_nobody_seen_there() -> None:
    """A reader within tag range that the LIDAR does not find standing free (it has stood
    there long enough to be in the map's walls) is still faced: the call is answered."""
    g = free_room()
    pose = np.array([-3.5, 0.0, math.pi / 2])
    look = Lookout(LookParams(approach_range_m=10.0, omega_rps=1.0))
    look.sensor_range_m = 10.0
    look.hear(0.0, np.array([-2.2, 0.5]), 1.0, sure=False, range_m=1.4,
              range_tolerance_m=0.3)
    tw = look.step(0.05, pose, walls_seen(pose), g, np.zeros((0, 2)))
    assert tw is not None and look.active and look.calls == 1 and look.calls_unseen == 0
