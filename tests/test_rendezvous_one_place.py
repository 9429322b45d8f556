"""Sightings of a robot standing in one place: beside a narrow sensor, the maps' square walls
give the turn the sightings cannot (``Merger._one_place``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.rendezvous import Sighting
from schemas.se2 import between, compose
from server.rendezvous.evidence import make_record
from tests.test_rendezvous_merger import two_robots

SIGMA_YAW = math.radians(6.0)    # a tag's yaw from a few metres: not informative


def sightings_of_one_place(T_true: np.ndarray, yaw_error_rad: float) -> list:
    """r1 seeing r2 from four places while r2 stands still at one; the tags' yaws all
    ``yaw_error_rad`` off (one geometry: their errors are shared)."""
    P_b = np.array([7.0, 6.5, 1.0])                    # r2, in its own map frame
    at_b = compose(T_true, P_b)                         # ... in r1's
    out = []
    for i, P_a in enumerate([np.array([3.0, 4.0, 0.5]), np.array([3.5, 3.0, 0.6]),
                             np.array([2.5, 3.5, 0.4]), np.array([3.2, 4.5, 0.3]),
                             np.array([2.8, 3.8, 0.5])]):
        rel = between(P_a, at_b)
        s = Sighting(float(np.hypot(rel[0], rel[1])), math.atan2(rel[1], rel[0]),
                     float(rel[2]) + yaw_error_rad, 0.03, 0.01, SIGMA_YAW)
        out.append(make_record((i + 1) * 1_000_000_000, "r1", "r2", s, (0, P_a), (0, P_b),
                               P_a, P_b, (0.03, 0.03, 0.01)))
    return out


def feed(core, records: list) -> list:   # type: ignore[no-untyped-def]
    found = []
    for rec in records:
        assert core.merger.verifier.add("team-r1", "team-r2", rec) is None   # one place
        p = core.merger._one_place("team-r1", "team-r2", rec.stamp_ns)
        if p is not None:
            found.append(p)
    return found


def test_one_place_beside_a_narrow_sensor_takes_the_square_walls_turn() -> None:
    core, T_true = two_robots()
    core.robots["r2"].slam.narrow = True
    found = feed(core, sightings_of_one_place(T_true, math.radians(7.0)))
    assert found, "no proposal from one place"
    p = found[-1]
    assert abs(math.degrees(p.T_ab[2] - T_true[2])) < 0.5       # the tags said 7° off
    assert np.hypot(*(p.T_ab[:2] - T_true[:2])) < 0.1
    assert core.tag_counters["one_place_proposals"] == len(found)
    core.merger.verify(p, "tags", {})                             # the maps agree
    assert core.merger.try_merge(p, 9_000_000_000) is not None
    assert len(core.teams) == 1


def test_one_place_waits_between_lidar_robots_or_when_the_tags_are_too_rough() -> None:
    core, T_true = two_robots()
    assert feed(core, sightings_of_one_place(T_true, math.radians(7.0))) == []
    core2, T2 = two_robots()
    core2.robots["r2"].slam.narrow = True
    # 50° off: the walls' nearest quarter turn is the wrong one, and it is not proposed
    # (the tags' own σ gives at most 18° from them)
    found = feed(core2, sightings_of_one_place(T2, math.radians(50.0)))
    assert found == []
    assert core2.tag_counters["one_place_proposals"] == 0


def sightings_of_a_short_path(T_true: np.ndarray, step_m: float) -> list:
    """r1 seeing r2 from one place while r2 drives ``step_m`` per sighting straight on (well
    under the metre that fixes the turn to a degree); the
    tags' yaws useless (σ 86°, 40° off), r1's range and bearing from its LIDAR."""
    P_a = np.array([3.0, 4.0, 0.5])
    out = []
    for i in range(10):
        P_b = np.array([7.0 + step_m * i, 6.5, 0.0])   # r2, in its own map frame
        rel = between(P_a, compose(T_true, P_b))
        s = Sighting(float(np.hypot(rel[0], rel[1])), math.atan2(rel[1], rel[0]),
                     float(rel[2]) + math.radians(40.0), 0.02, 0.004, math.radians(86.0))
        out.append(make_record((i + 1) * 1_000_000_000, "r1", "r2", s, (0, P_a), (0, P_b),
                               P_a, P_b, (0.03, 0.03, 0.01)))
    return out


def test_a_short_path_beside_a_narrow_sensor_takes_the_square_walls_turn() -> None:
    core, T_true = two_robots()
    core.robots["r2"].slam.narrow = True
    found = feed(core, sightings_of_a_short_path(T_true, 0.08))
    assert found, "no proposal from a short path"
    p = found[-1]
    assert abs(math.degrees(p.T_ab[2] - T_true[2])) < 0.5
    assert np.hypot(*(p.T_ab[:2] - T_true[:2])) < 0.1
    assert core.tag_counters["short_path_proposals"] == len(found)
    assert core.tag_counters["one_place_proposals"] == 0
    assert core.merger.try_merge(p, 9_000_000_000) is not None
    assert len(core.teams) == 1


def test_a_short_path_waits_between_lidar_robots_or_when_too_short() -> None:
    core, T_true = two_robots()
    assert feed(core, sightings_of_a_short_path(T_true, 0.08)) == []     # no narrow sensor
    core2, T2 = two_robots()
    core2.robots["r2"].slam.narrow = True
    # 18 cm in all: the places do not give the turn even to the 8° that picks a quarter
    assert feed(core2, sightings_of_a_short_path(T2, 0.02)) == []
    assert core2.tag_counters["short_path_proposals"] == 0


@pytest.mark.parametrize("turn_deg", [0.0, 90.0])
def test_square_turn_picks_the_quarter_nearest_the_rough_turn(turn_deg: float) -> None:
    from server.rendezvous.maps import square_turn

    core, T_true = two_robots()
    a, b = [core.robots["r1"].slam], [core.robots["r2"].slam]
    rough = T_true[2] + math.radians(turn_deg + 8.0)
    got = square_turn(a, b, rough, math.radians(20.0), 0.5)
    assert got is not None
    assert abs(math.degrees(got - T_true[2]) - turn_deg) < 0.5
    assert square_turn(a, b, rough, math.radians(5.0), 0.5) is None


def test_a_narrow_robots_whole_scans_are_tied_to_its_wide_teammates_map(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """After a merge, a wide robot's new keyframe ties its narrow teammate's whole scans near
    it to its map, each once; a narrow robot's own keyframes do not call for it."""
    import server.rendezvous.surgery as surgery_mod
    from tests.test_rendezvous_merger import proposal

    core, T_true = two_robots(refine_on_maps=False)
    core.robots["r2"].slam.narrow = True            # its 360° keyframes stand for whole scans
    _, link = core.surgery.own_frames_link("r1", "r2", T_true, np.array([0.02, 0.02, 0.01]),
                                           "marker", 9_000_000_000)
    assert core.merger.try_merge(proposal(T_true), 9_000_000_000, (link,),
                                 kind="marker") is not None
    team = core.fleet.team_of(core.robots["r1"])
    cross = sum(ln.record.kind == "cross" for ln in team.links)
    monkeypatch.setattr(surgery_mod, "WHOLE_TIE_RADIUS_M", 8.0)   # the two circles are 5 m apart
    core.cfg.teams.refine_on_maps = True
    kept = core.surgery._tie_wholes(core.robots["r1"], ["r2"], team.links)
    assert kept > 0
    assert sum(ln.record.kind == "cross" for ln in team.links) == cross + kept
    tries = core.surgery._whole_tries["r2"]
    assert sum(v == -1 for v in tries.values()) == kept
    assert core.surgery._tie_wholes(core.robots["r1"], ["r2"], team.links) <= \
        sum(0 <= v < surgery_mod.WHOLE_TIE_TRIES for v in tries.values())
    assert core.surgery._tie_wholes(core.robots["r2"], ["r1"], team.links) == 0   # r1 is wide
