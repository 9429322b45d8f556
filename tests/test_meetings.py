"""Meetings planned on a map-matched transform (server.rendezvous.matchdesk): how the robots
are steered, and how a meeting is settled — confirmed by a tag merge under the transform,
refuted by a merge under another one or by the time running out. A real core, fed the
simulator's scans of two robots in the small house."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.se2 import compose, inverse
from server.control import Obstacles
from server.core import ServerCore
from server.fleet.model import MergeRecord
from server.rendezvous import meetings
from server.rendezvous.mapmatch import Candidate, Hypothesis
from server.rendezvous.matchdesk import HypothesisEntry
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from tests.test_cluster_handover import step_messages
from tests.test_team_merge import WORLD, config

#: two robots 2.2 m apart in one room, facing each other
SPAWN = {"r1": (-8.0, 9.0, 0.0), "r2": (-6.0, 8.0, math.pi)}
T_TRUE = compose(inverse(np.array(SPAWN["r1"])), np.array(SPAWN["r2"]))


class _NoTags:
    def detect(self, *_args: object) -> object:
        return type("Found", (), {"sightings": []})()


@pytest.fixture
def core() -> ServerCore:
    """Both robots scanned for 3 s where they stand (no merge, no map matching)."""
    sim = Simulator(load_world(WORLD), SPAWN, SimParams(), seed=1)
    c = ServerCore(config(map_match=False))
    for _ in range(30):
        obs = sim.sense()
        scans, _ = step_messages(sim, _NoTags(), obs)
        for scan in scans.values():
            c.on_scan(scan)
        sim.advance()
    return c


def _hypothesis(T: np.ndarray, places: list[tuple[float, float]]) -> Hypothesis:
    members = tuple(Candidate(T, "ab"[k % 2], k, np.asarray(xy, dtype=float), 100.0, 100, 0,
                              0.99, 1000) for k, xy in enumerate(places))
    return Hypothesis(T, len(members), members, 0, 0.99)


def _plan(core: ServerCore, T: np.ndarray) -> HypothesisEntry:
    desk = core.matcher
    e = HypothesisEntry(0, 0, "team-r1", "team-r2", "r1", "r2", T, 3, 2, 1, 0, 0.99)
    desk.log.append(e)
    # the place: between the two robots, in free space of both maps
    meetings.arrange(desk, e, _hypothesis(T, [(1.0, -0.5), (0.8, -0.3), (1.2, -0.6)]),
                       core.robots["r1"].last_stamp_ns)
    return e


def test_a_meeting_sends_both_robots_to_one_place(core: ServerCore) -> None:
    e = _plan(core, T_TRUE)
    r1, r2 = core.robots["r1"], core.robots["r2"]
    assert e.status == "meeting" and r1.meeting is not None and r2.meeting is not None
    assert (r1.meeting.other, r2.meeting.other) == ("r2", "r1")
    # each goes to the place as its own map has it: the same spot in the world
    assert r1.meeting.target_xy is not None and r2.meeting.target_xy is not None
    w1 = compose(np.array(SPAWN["r1"]), np.array([*r1.meeting.target_xy, 0.0]))
    w2 = compose(np.array(SPAWN["r2"]), np.array([*r2.meeting.target_xy, 0.0]))
    assert math.hypot(*(w1[:2] - w2[:2])) < 0.05
    assert r2.meeting.path_xy is not None and len(r2.meeting.path_xy) >= 2
    # r2 is steered along its path (the navigator's own target is not used meanwhile)
    cmd = core.steering.meet(r2, Obstacles())
    assert cmd.v_mps > 0 or abs(cmd.omega_rps) > 0
    assert core.tag_counters["meetings"] == 1
    assert [ev.kind for ev in core.event_log][-1] == "meeting"


def test_a_merge_under_the_transform_confirms_it(core: ServerCore) -> None:
    e = _plan(core, T_TRUE)
    _merge(core, T_TRUE)
    core.matcher.tick(core.robots["r1"].last_stamp_ns)
    assert e.status == "confirmed"
    assert core.merges[-1].kind == "meeting"
    assert core.robots["r1"].meeting is None and core.robots["r2"].meeting is None


def test_a_merge_under_another_transform_refutes_it(core: ServerCore) -> None:
    e = _plan(core, T_TRUE)
    _merge(core, T_TRUE + np.array([3.0, 0.0, 0.0]))
    core.matcher.tick(core.robots["r1"].last_stamp_ns)
    assert e.status == "refuted"
    assert core.merges[-1].kind == "tags"


def test_a_meeting_that_does_not_happen_in_time_refutes_it(core: ServerCore) -> None:
    e = _plan(core, T_TRUE)
    r1 = core.robots["r1"]
    assert r1.meeting is not None
    late = int((r1.meeting.until_s + 1.0) * 1e9)
    core.matcher.tick(late)
    assert e.status == "refuted" and "did not meet" in e.reason
    assert r1.meeting is None and core.robots["r2"].meeting is None
    assert core.tag_counters["meetings_refuted"] == 1
    # a refuted transform is never used again: the same hypothesis plans no meeting
    meetings.arrange(core.matcher, e, _hypothesis(T_TRUE, [(1.0, -0.5)]), late)
    assert e.status == "refuted" and r1.meeting is None


def test_both_robots_at_their_places_unseen_refute_it_before_the_time_runs_out(
        core: ServerCore) -> None:
    """Under a wrong transform each robot reaches its own place; standing there
    ``MEET_SEEN_S`` with no merge refutes the meeting long before its time runs out (in a
    floor of offices alike, 70 s had been spent waiting at two places 17 m apart)."""
    wrong = T_TRUE + np.array([0.0, 0.6, 0.0])
    e = _plan(core, wrong)
    r1, r2 = core.robots["r1"], core.robots["r2"]
    assert r1.meeting is not None and r2.meeting is not None
    now = r1.last_stamp_ns
    # one robot there: it waits for the other
    r1.meeting.path_xy, r1.meeting.arrived_ns = None, now
    core.matcher.tick(now + int(meetings.MEET_SEEN_S * 1e9) + int(1e9))
    assert e.status == "meeting" and r1.meeting is not None
    # both there, not yet long enough
    r2.meeting.path_xy, r2.meeting.arrived_ns = None, now + int(2e9)
    core.matcher.tick(now + int((2 + meetings.MEET_SEEN_S - 1) * 1e9))
    assert e.status == "meeting"
    assert now * 1e-9 + 2 + meetings.MEET_SEEN_S + 1 < r1.meeting.until_s
    core.matcher.tick(now + int((2 + meetings.MEET_SEEN_S + 1) * 1e9))
    assert e.status == "refuted" and "saw no tag of each other" in e.reason
    assert r1.meeting is None and r2.meeting is None


def test_a_robot_that_reaches_its_place_is_marked_there(core: ServerCore) -> None:
    e = _plan(core, T_TRUE)
    r2 = core.robots["r2"]
    assert e.status == "meeting" and r2.meeting is not None and r2.meeting.path_xy is not None
    goal = r2.meeting.path_xy[-1]
    r2.pose = np.array([goal[0], goal[1], 0.0])
    cmd = core.steering.meet(r2, Obstacles(), 123)
    assert (cmd.v_mps, cmd.omega_rps) == (0.0, 0.0)
    assert r2.meeting.path_xy is None and r2.meeting.arrived_ns == 123


def test_a_meeting_too_far_away_is_not_planned(core: ServerCore) -> None:
    """Beyond ``meet_max_detour_m`` from every floor both maps know, no meeting."""
    teams = core.cfg.teams.model_copy(update={"meet_max_detour_m": 0.3})
    core.cfg = core.matcher.cfg = core.cfg.model_copy(update={"teams": teams})
    far = T_TRUE + np.array([0.0, 0.0, 0.0])
    e = HypothesisEntry(0, 0, "team-r1", "team-r2", "r1", "r2", far, 3, 2, 1, 0, 0.99)
    core.matcher.log.append(e)
    meetings.arrange(core.matcher, e, _hypothesis(far, [(60.0, 60.0)]),
                               core.robots["r1"].last_stamp_ns)
    assert e.status == "pending" and core.robots["r1"].meeting is None


def test_a_meeting_that_would_finish_the_exploration_is_planned_at_any_distance(
        core: ServerCore) -> None:
    """The same place, beyond ``meet_max_detour_m``: no meeting, unless the two maps joined
    would cover the threshold; then it is planned, with the time its paths take."""
    teams = core.cfg.teams.model_copy(update={"meet_max_detour_m": 0.3})
    core.cfg = core.matcher.cfg = core.cfg.model_copy(update={"teams": teams})
    places = [(1.0, -0.5), (0.8, -0.3), (1.2, -0.6)]
    e = HypothesisEntry(0, 0, "team-r1", "team-r2", "r1", "r2", T_TRUE, 3, 2, 1, 0, 0.99)
    core.matcher.log.append(e)
    now = core.robots["r1"].last_stamp_ns
    meetings.arrange(core.matcher, e, _hypothesis(T_TRUE, places), now)
    assert e.status == "pending" and core.robots["r1"].meeting is None
    meetings.arrange(core.matcher, e, _hypothesis(T_TRUE, places), now, finishing=True)
    assert e.status == "meeting" and core.robots["r1"].meeting is not None


def _merge(core: ServerCore, T: np.ndarray) -> None:
    """The two teams joined as a tag merge would (r2's team into r1's under ``T``)."""
    fleet = core.fleet
    r2 = fleet.robots["r2"]
    r2.team_id = "team-r1"
    fleet.teams["team-r1"].robot_ids.append("r2")
    fleet.retired_teams["team-r2"] = fleet.teams.pop("team-r2")
    fleet.merges.append(MergeRecord(r2.last_stamp_ns, "team-r1", "team-r2", ["r1"], ["r2"],
                                    [], T, np.eye(3), T, T, {}))


def test_the_union_of_two_maps_counts_their_overlap_once(core: ServerCore) -> None:
    """Under the true transform the two robots' maps of one room overlap; moved far apart
    they do not, and the union is the sum of the two."""
    from server.rendezvous.maps import union_area_m2

    core.progress.update(core.robots["r1"].last_stamp_ns)
    ga, gb = core.fleet.latest_grids["team-r1"], core.fleet.latest_grids["team-r2"]
    area_a = float((ga.free | ga.occupied).sum()) * ga.geometry.cell_area_m2
    area_b = float((gb.free | gb.occupied).sum()) * gb.geometry.cell_area_m2
    apart = union_area_m2(ga, gb, T_TRUE + np.array([60.0, 0.0, 0.0]))
    assert apart == pytest.approx(area_a + area_b, rel=0.05)   # b sampled every 0.2 m
    together = union_area_m2(ga, gb, T_TRUE)
    assert max(area_a, area_b) <= together < 0.8 * (area_a + area_b)


def test_a_transform_seen_from_one_map_is_met_only_if_the_maps_joined_would_finish(
        core: ServerCore) -> None:
    """Places of one team's map found in the other's, none the other way: no meeting while
    the two maps joined under it leave the building unexplored; a meeting once they would
    cover the threshold."""
    desk, now = core.matcher, core.robots["r1"].last_stamp_ns
    core.progress.update(now)
    places = [(1.0, -0.5), (0.8, -0.3), (1.2, -0.6), (0.9, -0.7)]
    members = tuple(Candidate(T_TRUE, "b", k, np.asarray(xy, dtype=float), 100.0, 100, 0,
                              0.99, 1000) for k, xy in enumerate(places))
    h = Hypothesis(T_TRUE, 4, members, 1, 0.99)
    assert h.side_support("a") == 0 and not h.accepted(desk.params)
    e = HypothesisEntry(0, now, "team-r1", "team-r2", "r1", "r2", T_TRUE, 4, 0, 4, 1, 0.99)
    desk.log.append(e)
    desk._decide(e, h, now)
    assert e.status == "pending" and core.robots["r1"].meeting is None
    assert e.union_coverage is not None and e.union_coverage < 0.5   # the room of 374 m²
    # the same maps, in a building no larger than what they hold together
    explore = core.cfg.explore.model_copy(update={
        "total_area_m2": e.union_coverage * core.cfg.explore.total_area_m2 / 0.99})
    core.cfg = core.cfg.model_copy(update={"explore": explore})
    desk.cfg = core.cfg
    desk._decide(e, h, now)
    assert e.union_coverage >= core.cfg.explore.coverage_threshold
    assert e.status == "meeting" and core.robots["r1"].meeting is not None


def test_a_place_in_a_walls_margin_moves_to_floor_free_on_both_maps(core: ServerCore) -> None:
    """The transform is good to decimetres, and a place cut from one map may lie in the
    other's unknown: a meeting's place moves to the nearest cell free on both maps, and
    each robot can drive to it. Where the other map knows nothing near, there is none."""
    from schemas.se2 import transform_points

    desk, r1, r2 = core.matcher, core.robots["r1"], core.robots["r2"]
    la, lb = meetings._layer(desk, r1), meetings._layer(desk, r2)
    rc = np.argwhere(~np.isfinite(la.cost))
    xy = la.geometry.cell_to_world(rc)
    near = np.flatnonzero(np.hypot(*(xy - r1.pose[:2]).T) < 3.0)
    margin = [k for k in near if la.escape(tuple(rc[k]), 0.3) not in (None, tuple(rc[k]))]
    assert margin, "no wall margin near r1"
    goal = xy[margin[0]]
    found = meetings._common_place(la, lb, T_TRUE, goal)
    assert found is not None
    p_a, p_b = found
    assert 0 < math.hypot(*(p_a - goal)) <= meetings.PLACE_SEARCH_M
    assert np.allclose(transform_points(T_TRUE, p_b[None, :])[0], p_a, atol=1e-9)
    why: list[str] = []
    assert meetings._path(la, r1, p_a, why) is not None, why
    assert meetings._path(lb, r2, p_b, why) is not None, why
    assert meetings._common_place(la, lb, T_TRUE + np.array([60.0, 0.0, 0.0]), goal) is None


def test_without_a_place_near_the_submaps_the_robots_meet_on_floor_both_maps_know(
        core: ServerCore) -> None:
    """A place far from anything both maps know: no meeting, unless the maps joined would
    finish the exploration; then the robots are sent to the floor free on both maps nearest
    to them, the same spot in the world."""
    e = HypothesisEntry(0, 0, "team-r1", "team-r2", "r1", "r2", T_TRUE, 3, 2, 1, 0, 0.99)
    core.matcher.log.append(e)
    r1, r2 = core.robots["r1"], core.robots["r2"]
    far = _hypothesis(T_TRUE, [(40.0, 40.0)] * 3)
    meetings.arrange(core.matcher, e, far, r1.last_stamp_ns)
    assert e.status == "pending" and r1.meeting is None and r2.meeting is None
    meetings.arrange(core.matcher, e, far, r1.last_stamp_ns, finishing=True)
    assert e.status == "meeting" and r1.meeting is not None and r2.meeting is not None
    assert r1.meeting.target_xy is not None and r2.meeting.target_xy is not None
    w1 = compose(np.array(SPAWN["r1"]), np.array([*r1.meeting.target_xy, 0.0]))
    w2 = compose(np.array(SPAWN["r2"]), np.array([*r2.meeting.target_xy, 0.0]))
    assert math.hypot(*(w1[:2] - w2[:2])) < 0.05
    assert math.hypot(*(r1.meeting.target_xy - r1.pose[:2])) < 5.0
