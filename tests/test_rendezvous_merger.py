"""The merger on its own: two robots' graphs built from scans of a drawn floor plan (no
simulator), a proposal refused, one deferred, one committed and undone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factors.rendezvous import Sighting
from schemas import Scan
from schemas.messages import quantise_ranges_mm
from schemas.se2 import between, compose
from server.config import ServerConfig
from server.core import ServerCore
from server.rendezvous.evidence import MergeProposal, make_record
from server.rendezvous.merger import MergeDeferred, MergeRefused

#: a 10 m × 8 m room with a box and a wall stub in it (no symmetry to fool a matcher)
WALLS = np.array([
    [0, 0, 10, 0], [10, 0, 10, 8], [10, 8, 0, 8], [0, 8, 0, 0],
    [6, 2, 7, 2], [7, 2, 7, 4], [7, 4, 6, 4], [6, 4, 6, 2],
    [3, 8, 3, 5.5]], dtype=np.float64)
BEAMS = 360


def ranges_from(pose: np.ndarray, walls: np.ndarray) -> np.ndarray:
    """Ranges [m] of BEAMS beams from ``pose`` to the nearest wall segment."""
    a = pose[2] - math.pi + 2 * math.pi * np.arange(BEAMS) / BEAMS
    d = np.stack([np.cos(a), np.sin(a)], 1)[:, None, :]          # (B, 1, 2)
    p, q = walls[None, :, :2], walls[None, :, 2:]                 # (1, W, 2)
    e = q - p
    w = p - pose[:2]
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / den
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / den
    t = np.where((den != 0) & (t > 0) & (u >= 0) & (u <= 1), t, np.inf)
    return t.min(axis=1)


def drive(core: ServerCore, rid: str, centre: tuple[float, float], steps: int,
          walls: np.ndarray = WALLS, phase: float = 0.0) -> np.ndarray:
    """Scans of ``rid`` circling ``centre`` (radius 1 m, 0.3 rad/s, 10 Hz, exact odometry);
    returns its true start pose."""
    start = None
    for k in range(steps):
        a = phase + 0.03 * k
        pose = np.array([centre[0] + math.cos(a), centre[1] + math.sin(a), a + math.pi / 2])
        start = pose if start is None else start
        r = ranges_from(pose, walls)
        core.on_scan(Scan(robot_id=rid, seq=k + 1, stamp_ns=k * 100_000_000,
                          odom_pose=(float(pose[0]), float(pose[1]), float(pose[2])),
                          angle_min_rad=-math.pi, angle_increment_rad=2 * math.pi / BEAMS,
                          range_min_mm=50, range_max_mm=12000,
                          ranges_mm=quantise_ranges_mm(r, 0.05, 12.0)))
    assert start is not None
    return start


def two_robots(refine_on_maps: bool = True, apart_m: float = 0.0
               ) -> tuple[ServerCore, np.ndarray]:
    """r1 and r2 each in a team of their own; ``apart_m``: r2 in a copy of the room that far
    off along x. Returns the core and the true transform from r2's map frame to r1's."""
    cfg = ServerConfig.model_validate({"robots": ["r1", "r2"],
                                       "teams": {"refine_on_maps": refine_on_maps}})
    core = ServerCore(cfg, navigate=False)
    s1 = drive(core, "r1", (2.5, 3.0), 160)
    walls_b = WALLS + np.array([apart_m, 0.0, apart_m, 0.0])
    s2 = drive(core, "r2", (7.5 + apart_m, 6.0), 160, walls_b, phase=1.0)
    assert len(core.teams) == 2
    assert all(len(r.slam.keyframes) >= 3 for r in core.robots.values())
    return core, between(s1, s2)


def proposal(T: np.ndarray, records: tuple = ()) -> MergeProposal:
    C = np.diag([0.02 ** 2, 0.02 ** 2, math.radians(0.5) ** 2])
    return MergeProposal("team-r1", "team-r2", records, T, C, T)


def test_a_proposal_the_maps_contradict_is_refused_and_its_evidence_dropped() -> None:
    core, T_true = two_robots()
    T_bad = compose(T_true, np.array([1.5, -1.0, math.radians(20)]))
    with pytest.raises(MergeRefused, match="maps"):
        core.merger.verify(proposal(T_bad), "tags", {})
    assert core.merger.try_merge(proposal(T_bad), 9_000_000_000) is None
    assert len(core.teams) == 2 and not core.merges
    assert core.tag_counters["merges_rejected"] == 1
    assert [e.kind for e in core.event_log].count("merge_rejected") == 1


def test_far_sightings_without_a_map_match_are_deferred_not_refused() -> None:
    """Sightings located by the LIDAR from afar, and maps that do not overlap yet: the merge
    waits (the evidence stays) rather than join maps a degree off."""
    core, T_true = two_robots(apart_m=30.0)
    far = core.cfg.teams.max_sighting_range_m + 2.0
    s = Sighting(far, 0.0, math.pi, 0.05, 0.01, 0.3)
    P = np.zeros(3)
    rec = make_record(0, "r1", "r2", s, (0, P), (0, P), P, P, (0.05, 0.05, 0.01))
    with pytest.raises(MergeDeferred):
        core.merger.verify(proposal(T_true, (rec,)), "tags", {})
    assert core.merger.try_merge(proposal(T_true, (rec,)), 9_000_000_000) is None
    assert len(core.teams) == 2
    assert core.tag_counters["merges_deferred"] == 1
    assert core.tag_counters["merges_rejected"] == 0
    # the same sighting from within tag range is not deferred
    near = make_record(0, "r1", "r2", Sighting(1.0, 0.0, math.pi, 0.05, 0.01, 0.3),
                       (0, P), (0, P), P, P, (0.05, 0.05, 0.01))
    info: dict[str, float] = {}
    core.merger.verify(proposal(T_true, (near,)), "tags", info)
    assert info["map_match_tries"] == 0 and info["wall_cells"] == 0   # maps apart: no check


def test_beside_a_narrow_sensor_far_sightings_merge_when_the_option_is_on() -> None:
    """A depth camera's short views seldom overlap the other team's map early: with
    ``teams.narrow_far_sightings`` a team with such a robot merges on far sightings that no
    map match confirmed, if they turn the maps' square walls onto each other; without it, or
    between two LIDAR robots, the merge waits."""
    core, T_true = two_robots(apart_m=30.0)
    far = core.cfg.teams.max_sighting_range_m + 2.0
    P = np.zeros(3)
    rec = make_record(0, "r1", "r2", Sighting(far, 0.0, math.pi, 0.05, 0.01, 0.3),
                      (0, P), (0, P), P, P, (0.05, 0.05, 0.01))
    core.cfg.teams.narrow_far_sightings = True
    with pytest.raises(MergeDeferred):                      # two LIDAR robots: it waits
        core.merger.verify(proposal(T_true, (rec,)), "tags", {})
    core.robots["r2"].slam.narrow = True
    core.merger.verify(proposal(T_true, (rec,)), "tags", {})   # goes through
    # ... unless the sightings turn one map's square walls off the other's
    T_turned = compose(T_true, np.array([0.0, 0.0, math.radians(4.0)]))
    with pytest.raises(MergeDeferred):
        core.merger.verify(proposal(T_turned, (rec,)), "tags", {})
    core.cfg.teams.narrow_far_sightings = False
    with pytest.raises(MergeDeferred):
        core.merger.verify(proposal(T_true, (rec,)), "tags", {})


def test_a_merge_is_committed_then_undone_back_into_two_teams() -> None:
    core, T_true = two_robots(refine_on_maps=False)
    r2 = core.robots["r2"]
    own_before = r2.slam.pose.copy()
    sig = np.array([0.02, 0.02, 0.01])
    _, link = core.surgery.own_frames_link("r1", "r2", T_true, sig, "marker", 9_000_000_000)
    rec = core.merger.try_merge(proposal(T_true), 9_000_000_000, (link,), kind="marker")
    assert rec is not None and len(core.teams) == 1
    team = core.teams["team-r1"]
    assert team.robot_ids == ["r1", "r2"] and r2.team_id == "team-r1"
    assert np.allclose(r2.pose[:2], compose(T_true, own_before)[:2], atol=0.1)
    assert core.merger.undo(team, 9_500_000_000, ("r1", "r2"))
    assert sorted(core.teams) == ["team-r1", "team-r2"]
    assert core.robots["r1"].team_id == "team-r1" and r2.team_id == "team-r2"
    assert rec.undone_stamp_ns == 9_500_000_000
    assert core.tag_counters["merges_undone"] == 1
    assert np.allclose(r2.pose[:2], own_before[:2], atol=0.1)   # back in its own frame
    assert r2.slam.graph is not core.robots["r1"].slam.graph
    assert core.event_log[-1].kind == "merge_undone"


def test_an_undo_the_maps_still_support_is_overruled() -> None:
    core, T_true = two_robots(refine_on_maps=True)
    _, link = core.surgery.own_frames_link("r1", "r2", T_true, np.array([0.02, 0.02, 0.01]),
                                           "marker", 9_000_000_000)
    assert core.merger.try_merge(proposal(T_true), 9_000_000_000, (link,),
                                 kind="marker") is not None
    assert core.merges[0].agreement["map_matches"] > 0
    team = core.teams["team-r1"]
    assert not core.merger.undo(team, 9_500_000_000, ("r1", "r2"))
    assert len(core.teams) == 1 and core.merges[0].undone_stamp_ns is None
    assert core.tag_counters["contradictions_overruled"] == 1
