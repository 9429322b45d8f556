"""Two robots meet in the dissertation's small house: the simulator renders their tags, the
agent's detector reads them, and the server core merges the two graphs into one team — or,
fed sightings that put the other robot in the wrong place, refuses to.

The loop runs in one process (simulator → scans and detections → ``ServerCore`` → commands),
so it is quick and exactly repeatable; the process-level path is the demo's."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import gtsam
import msgspec
import numpy as np
import pytest

from bench.support.mission import scan_of
from robot_agent.aruco import TagDetector
from schemas import TagDetection, TagDetections
from schemas.se2 import between, compose, pose_distance
from schemas.tags import CameraMount, TagLayout
from server.command.operator import Errand
from server.config import ServerConfig
from server.control import Obstacles, PurePursuit
from server.core import ServerCore
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from tests.conftest import DATA

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow

WORLD = DATA / "worlds" / "thesis" / "house_small.world"
SPAWN = {"r1": (-8.0, 9.0, 0.0), "r2": (-6.0, 8.0, math.pi)}


def config(robots: tuple[str, ...] = ("r1", "r2"), **teams: object) -> ServerConfig:
    return ServerConfig.model_validate({
        "robots": list(robots),
        "slam": {"grid": {"resolution_m": 1 / 15}},
        "explore": {"total_area_m2": 374.5, "coverage_threshold": 0.98},
        "teams": teams,
    })


Relabel = Callable[[int, str, TagDetection], TagDetection]


def run(steps: int, falsify: bool = False, false_until: int = 0,
        cfg: ServerConfig | None = None, spawn: dict[str, tuple[float, float, float]] = SPAWN,
        relabel: Relabel | None = None,
        truth: dict[int, dict[str, tuple[float, float, float]]] | None = None
        ) -> tuple[ServerCore, Simulator]:
    """``relabel(step, observer, detection)`` may change a detection before the server
    hears it; ``truth`` gets every robot's true pose at each scan's stamp."""
    sim = Simulator(load_world(WORLD), spawn, SimParams(), seed=3)
    core = ServerCore(cfg or config())
    detector = TagDetector(TagLayout(), CameraMount())
    K = sim.p.camera.camera.K
    for step in range(steps):
        obs = sim.sense()
        if truth is not None:
            poses = {rid: [float(v) for v in sim.robots[rid].pose] for rid in spawn}
            truth[obs.stamp_ns] = {rid: (p[0], p[1], p[2]) for rid, p in poses.items()}
        wrong = falsify or step < false_until
        for rid in spawn:
            cmd = core.on_scan(scan_of(sim, obs, rid))
            sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
        for rid, frame in obs.frames.items():
            found = detector.detect(frame.image, K, rid)
            dets = [TagDetection(tag_id=s.tag_id, observed_robot_id=s.robot_id,
                                 range_m=s.range_m + (1.5 if wrong else 0.0),
                                 bearing_rad=s.bearing_rad + (0.4 if wrong else 0.0),
                                 yaw_rad=s.yaw_rad, sigma_range_m=s.sigma_range_m,
                                 sigma_bearing_rad=s.sigma_bearing_rad,
                                 sigma_yaw_rad=s.sigma_yaw_rad)
                    for s in found.sightings]
            if relabel is not None:
                dets = [relabel(step, rid, d) for d in dets]
            if dets:
                core.on_tags(TagDetections(robot_id=rid, seq=obs.step + 1,
                                           stamp_ns=obs.stamp_ns, detections=dets))
        sim.advance()
    return core, sim


@pytest.fixture(scope="module")
def met() -> tuple[ServerCore, Simulator]:
    return run(250)


def test_robots_that_see_each_other_become_one_team(met: tuple[ServerCore, Simulator]) -> None:
    core, _ = met
    assert core.tag_counters["used"] > 10
    assert len(core.merges) == 1 and len(core.teams) == 1
    team = next(iter(core.teams.values()))
    assert sorted(team.robot_ids) == ["r1", "r2"]
    assert {core.robots[r].team_id for r in SPAWN} == {team.team_id}
    assert any(e.kind == "merge" and e.transform is not None and e.covariance is not None
               for e in core.event_log)
    # both robots now plan on one grid, and share one graph
    assert core.robots["r1"].slam.graph is core.robots["r2"].slam.graph


def test_the_merge_transform_is_accurate_and_beats_the_direct_method(
        met: tuple[ServerCore, Simulator]) -> None:
    core, _ = met
    m = core.merges[0]
    # each robot's own map frame is its first pose: the truth is their spawn poses
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))

    def err(T: np.ndarray) -> tuple[float, float]:
        return pose_distance(between(T_true, T))

    joint, direct = err(m.T_joint), err(m.T_direct_first)
    assert joint[0] <= 0.05 and joint[1] <= math.radians(1.0)
    assert joint[0] < direct[0]


def test_team_poses_stay_on_the_truth(met: tuple[ServerCore, Simulator]) -> None:
    core, sim = met
    r1_start = np.array(SPAWN["r1"])
    for rid in SPAWN:
        truth = np.array(sim.robots[rid].pose)
        est_world = compose(r1_start, core.robots[rid].pose)  # team frame = r1's first pose
        assert math.hypot(*(est_world[:2] - truth[:2])) < 0.1


def test_sightings_that_place_the_robot_wrongly_do_not_merge() -> None:
    # (read as far as 5 m, so that the false views, placed 1.5 m too far, are all weighed)
    core, _ = run(250, falsify=True, cfg=config(max_sighting_range_m=5.0))
    assert core.tag_counters["used"] > 10
    assert not core.merges
    assert len(core.teams) == 2


def test_a_wrong_merge_contradicted_by_later_sightings_is_undone() -> None:
    """Without the map check, false sightings merge the robots wrongly; the true sightings
    that follow disagree with the joint graph, and the merge is taken back."""
    core, _ = run(400, false_until=40, cfg=config(max_conflict_ratio=1.0, max_sighting_range_m=5.0))
    assert core.merges and core.merges[0].undone_stamp_ns is not None
    assert core.tag_counters["merges_undone"] >= 1
    assert any(e.kind == "merge_undone" for e in core.event_log)
    # the robots went back to their own teams and graphs (and may have merged again, rightly)
    if len(core.teams) == 1:
        m = core.merges[-1]
        assert m.undone_stamp_ns is None
        T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
        d = between(T_true, m.T_joint)
        assert math.hypot(d[0], d[1]) < 0.1
    else:
        assert core.robots["r1"].slam.graph is not core.robots["r2"].slam.graph


def test_sightings_of_unknown_robots_or_oneself_are_counted_not_fatal() -> None:
    core = ServerCore(config())
    bad = TagDetection(tag_id=1, observed_robot_id="r9", range_m=2.0, bearing_rad=0.0,
                       yaw_rad=0.0, sigma_range_m=0.1, sigma_bearing_rad=0.1, sigma_yaw_rad=0.1)
    me = replace_id(bad, "r1")
    core.on_tags(TagDetections(robot_id="r1", seq=1, stamp_ns=10, detections=[bad, me]))
    core.on_tags(TagDetections(robot_id="r1", seq=2, stamp_ns=5 * 10**9, detections=[]))
    assert core.tag_counters["self"] == 1
    assert core.tag_counters["unknown_robot"] == 1


def replace_id(d: TagDetection, rid: str) -> TagDetection:

    return msgspec.structs.replace(d, observed_robot_id=rid)



def test_robots_at_known_start_poses_are_one_team_from_their_first_scan() -> None:
    core, sim = run(40, cfg=config(start_poses={r: list(p) for r, p in SPAWN.items()}))
    assert len(core.merges) == 1 and core.merges[0].kind == "start"
    assert core.merges[0].stamp_ns == 0 and len(core.teams) == 1
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
    d = between(T_true, core.merges[0].T_joint)
    assert math.hypot(d[0], d[1]) < 0.05 and abs(d[2]) < math.radians(1.0)
    team = next(iter(core.teams.values()))
    start = np.array(SPAWN[core.robots[team.anchor].robot_id])
    for rid in SPAWN:
        truth = np.array(sim.robots[rid].pose)
        assert math.hypot(*(compose(start, core.robots[rid].pose)[:2] - truth[:2])) < 0.1


def test_a_wrong_start_pose_is_refused_by_the_map_check() -> None:
    wrong = {"r1": list(SPAWN["r1"]), "r2": [-6.0, 8.0, math.pi / 2]}  # turned by 90°
    core, _ = run(5, cfg=config(start_poses=wrong))
    assert core.tag_counters["merges_rejected"] >= 1
    assert any(e.kind == "merge_rejected" and e.stamp_ns == 0 for e in core.event_log)
    assert all(m.kind == "tags" for m in core.merges)  # they may still meet by their tags
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
    for m in core.merges:
        d = between(T_true, m.T_joint)
        assert math.hypot(d[0], d[1]) < 0.1


def test_a_tag_read_from_afar_calls_both_robots_together() -> None:
    """Too far to merge on, a sighting still tells the reader where the other robot is and
    the robot that was seen roughly where the reader stands."""
    core, _ = run(3, cfg=config(min_sightings=100))          # never merged here
    r1, r2 = core.robots["r1"], core.robots["r2"]
    assert r1.team_id != r2.team_id
    far = TagDetection(tag_id=2, observed_robot_id="r2", range_m=6.0, bearing_rad=0.5,
                       yaw_rad=math.pi, sigma_range_m=0.2, sigma_bearing_rad=0.02,
                       sigma_yaw_rad=0.5)
    core.on_tags(TagDetections(robot_id="r1", seq=9, stamp_ns=r1.last_stamp_ns,
                               detections=[far]))
    assert core.tag_counters["too_far"] >= 1                  # no evidence for a merge ...
    assert r1.look.call is not None and r2.look.call is not None   # ... but a call to both
    # located by the LIDAR off r2's body, the same sighting is good evidence at 6 m

    too_far, used = core.tag_counters["too_far"], core.tag_counters["used"]
    fixed = msgspec.structs.replace(far, located_by="lidar", sigma_range_m=0.02,
                                    sigma_bearing_rad=0.004)
    core.on_tags(TagDetections(robot_id="r1", seq=10, stamp_ns=r1.last_stamp_ns,
                               detections=[fixed]))
    assert core.tag_counters["too_far"] == too_far and core.tag_counters["used"] == used + 1
    xy, tol, sure, _ = r1.look.call
    expect = compose(r1.pose, np.array([6.0 * math.cos(0.5), 6.0 * math.sin(0.5), 0.0]))
    assert sure and math.hypot(*(xy - expect[:2])) < 1e-9 and tol < 1.0
    xy, tol, sure, _ = r2.look.call
    back = compose(r2.pose, between(np.array([6.0 * math.cos(0.5), 6.0 * math.sin(0.5),
                                              math.pi]), np.zeros(3)))
    assert not sure and math.hypot(*(xy - back[:2])) < 1e-9 and tol >= 2.0
    # a sighting with a NaN in it calls nobody (and neither does one within a team)
    r1.look.call = r2.look.call = None
    nan = msgspec.structs.replace(far, bearing_rad=float("nan"))
    core.on_tags(TagDetections(robot_id="r1", seq=10, stamp_ns=r1.last_stamp_ns,
                               detections=[nan]))
    assert r1.look.call is None and r2.look.call is None


def test_robots_of_other_teams_that_saw_each_other_keep_clear_of_each_other() -> None:
    """A camera turned away on its tower does not see the robot beside it: after a tag
    sighting, each robot of the pair knows where the other's team frame lies in its own, and
    one whose scans are narrow keeps clear of the other robot, wherever that robot's own pose
    puts it, for ``control.sighted_robot_s``, as of a teammate."""
    core, _ = run(3, cfg=config(min_sightings=100))          # never merged here
    r1, r2 = core.robots["r1"], core.robots["r2"]
    assert r1.team_id != r2.team_id and not r1.sighted and not r2.sighted
    assert len(core.fleet.others_in_robot_frame(r1)) == 0
    near = TagDetection(tag_id=2, observed_robot_id="r2", range_m=0.8, bearing_rad=-0.3,
                        yaw_rad=math.pi, sigma_range_m=0.02, sigma_bearing_rad=0.01,
                        sigma_yaw_rad=0.1)
    core.on_tags(TagDetections(robot_id="r1", seq=9, stamp_ns=r1.last_stamp_ns,
                               detections=[near]))
    assert r1.sighted and r2.sighted
    # a LIDAR robot sees the other: only a robot whose scans are narrow needs this
    assert len(core.fleet.others_in_robot_frame(r1)) == 0
    r1.slam.narrow = r2.slam.narrow = True
    (seen,) = core.fleet.others_in_robot_frame(r1)   # where the sighting put r2
    assert math.hypot(*(seen - [0.8 * math.cos(-0.3), 0.8 * math.sin(-0.3)])) < 0.3
    (back,) = core.fleet.others_in_robot_frame(r2)   # and r1, seen from r2 facing it
    assert math.hypot(*back) == pytest.approx(math.hypot(*seen), abs=1e-6) and back[0] > 0
    # it follows the other robot's own pose
    r2.pose = r2.pose + np.array([0.5, 0.0, 0.0])
    (moved,) = core.fleet.others_in_robot_frame(r1)
    assert math.hypot(*(moved - seen)) == pytest.approx(0.5, abs=1e-6)
    from server.control.geometry import Twist
    from server.control.vfh import Vfh

    # the steering avoids it: straight at it, the reactive layer slows or turns away
    ahead = Vfh().evaluate(Twist(0.3, 0.0), float(np.arctan2(seen[1], seen[0])),
                           np.zeros((0, 2)), core.fleet.others_in_robot_frame(r1))
    assert math.hypot(*seen) > 2.0 or ahead.twist.v_mps < 0.3 or ahead.twist.omega_rps != 0
    # kept for control.sighted_robot_s of the robot's own stamps, then forgotten
    keep = core.cfg.control.sighted_robot_s
    r1.last_stamp_ns = r1.sighted["r2"].stamp_ns + int((keep - 0.1) * 1e9)
    assert len(core.fleet.others_in_robot_frame(r1)) == 1
    r1.last_stamp_ns += int(0.2e9)
    assert len(core.fleet.others_in_robot_frame(r1)) == 0
    # a robot that vanished, or a merge since (the team frames changed), places nobody
    r2.last_stamp_ns = r2.sighted["r1"].stamp_ns
    r1.alive = False
    assert len(core.fleet.others_in_robot_frame(r2)) == 0
    r1.alive = True
    assert len(core.fleet.others_in_robot_frame(r2)) == 1
    r2.sighted["r1"] = r2.sighted["r1"]._replace(other_team="team-gone")
    assert len(core.fleet.others_in_robot_frame(r2)) == 0


def test_an_operators_errand_keeps_clear_of_a_robot_a_narrow_sensor_saw() -> None:
    """The operator sends a depth-camera robot straight through where another team's robot
    stands, which it has just read the tag of: the errand's command keeps clear of that robot
    as exploring would (one driver, one set of obstacles, for every behaviour)."""
    core, _ = run(3, cfg=config(min_sightings=100))
    r1, r2 = core.robots["r1"], core.robots["r2"]
    near = TagDetection(tag_id=2, observed_robot_id="r2", range_m=0.6, bearing_rad=0.0,
                        yaw_rad=math.pi, sigma_range_m=0.02, sigma_bearing_rad=0.01,
                        sigma_yaw_rad=0.1)
    core.on_tags(TagDetections(robot_id="r1", seq=9, stamp_ns=r1.last_stamp_ns,
                               detections=[near]))
    r1.slam.narrow = r2.slam.narrow = True
    (seen,) = core.fleet.others_in_robot_frame(r1)
    assert math.hypot(*seen) < 0.8 and abs(seen[1]) < 0.2      # straight ahead
    goal = compose(r1.pose, np.array([3.0, 0.0, 0.0]))[:2]
    path = np.array([r1.pose[:2], goal])
    core.orders.errands["r1"] = Errand("goto", r1.team_id, (float(goal[0]), float(goal[1])),
                                       path, PurePursuit(r1.nav.pursuit.params))
    beams = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    cmd = core.steering.command(r1, r1.last_stamp_ns, np.full(360, np.inf), beams)
    free = core.cfg.control.v_mps
    assert cmd.v_mps < 0.9 * free or abs(cmd.omega_rps) > 0.05, cmd


def test_a_robot_whose_team_is_done_still_answers_a_robot_left_alone() -> None:
    core, _ = run(3, cfg=config(min_sightings=100))
    r1 = core.robots["r1"]
    r1.nav.finish("team coverage reached")
    assert r1.nav.mode == "done"
    r1.look.call = None
    r1.look.next_s = -math.inf
    r1.look.hear(r1.last_stamp_ns * 1e-9, compose(r1.pose, np.array([-1.5, 0.0, 0.0]))[:2],
                 1.0, sure=False)                           # someone just behind it
    tw = core.steering.look(r1, r1.last_stamp_ns * 1e-9 + 0.05, Obstacles())
    assert tw is not None and tw.v_mps == 0.0 and tw.omega_rps != 0.0   # turning to face it


def test_robots_range_out_until_every_robot_is_in_their_team() -> None:
    """λ is ``seek_lam`` (nearest targets first) while a robot that is alive is outside the
    team, and the configured λ once none is (here: the other robot vanished)."""
    cfg = config(min_sightings=100)
    cfg = cfg.model_copy(update={"explore": cfg.explore.model_copy(
        update={"lam": 0.3, "seek_lam": 0.9})})
    core, _ = run(12, cfg=cfg)

    def lam(rid: str) -> float:
        return float(core.robots[rid].nav.explorer.params.lam)

    assert len(core.teams) == 2 and lam("r1") == lam("r2") == 0.9
    core.set_alive("r2", False)
    core.progress.set_lambda()
    assert lam("r1") == 0.3
    core.set_alive("r2", True)
    core.progress.set_lambda()
    assert lam("r1") == 0.9


def test_a_team_keeps_matching_each_robots_new_keyframes_against_the_others_maps(
        met: tuple[ServerCore, Simulator]) -> None:
    core, _ = met
    team = next(iter(core.teams.values()))
    cross = [ln for ln in team.links if ln.record.kind == "cross"]
    at_merge = int(core.merges[0].agreement["map_matches"])
    assert len(cross) > at_merge       # more matches came after the merge, as the robots went on
    assert all(ln.record.index is not None for ln in cross)
    assert {ln.b for ln in cross[at_merge:]} <= {"r1", "r2"}


def misread(after_step: int, seen: str, read_as: str) -> Relabel:
    """From ``after_step`` on, r1 reads ``seen``'s tag as ``read_as``'s (a misread id that
    persists)."""

    def relabel(step: int, observer: str, d: TagDetection) -> TagDetection:
        if step >= after_step and observer == "r1" and d.observed_robot_id == seen:
            return msgspec.structs.replace(d, observed_robot_id=read_as)
        return d
    return relabel


def test_a_misread_tag_that_puts_a_robot_on_a_teammate_does_not_split_the_team() -> None:
    """All three robots meet and merge; then r1 reads r3's tag as r2's, frame after frame. The
    sightings place r2 where r3 stands, which the team's graph explains by a misread tag:
    they neither count against the merge nor undo it."""
    spawn = {**SPAWN, "r3": (-7.0, 7.0, 1.2)}
    core, _ = run(150, cfg=config(("r1", "r2", "r3")), spawn=spawn,
                  relabel=misread(40, "r3", "r2"))
    assert len(core.teams) == 1 and len(core.merges) == 2
    assert all(m.undone_stamp_ns is None for m in core.merges)
    assert max(m.stamp_ns for m in core.merges) < 4e9        # merged before the misreading
    assert core.tag_counters["misread"] >= 10
    assert core.tag_counters["merges_undone"] == 0


def test_a_misread_tag_does_not_merge_a_robot_that_is_elsewhere() -> None:
    """r1 and r2 start as one team (known start poses); r3 explores far off. r1 reads r2's
    tag as r3's: sightings that say r3 stands where r1's teammate r2 is are taken as misread,
    not as evidence for merging r3, and call neither robot."""
    spawn = {**SPAWN, "r3": (4.0, -9.0, math.pi)}
    cfg = config(("r1", "r2", "r3"), start_poses={r: list(SPAWN[r]) for r in ("r1", "r2")})
    core, _ = run(60, cfg=cfg, spawn=spawn, relabel=misread(0, "r2", "r3"))
    assert [m.kind for m in core.merges] == ["start"]
    assert core.robots["r3"].team_id != core.robots["r1"].team_id
    # nor as a call: neither r1 nor r3 drove off to find the other (before, r1 answered
    # and drove up to r2, and r3 turned about; the nearer sightings were then placed and
    # taken for misread there)
    assert core.tag_counters["calls_misread"] >= 8
    assert [core.robots[r].look.calls for r in ("r1", "r2", "r3")] == [0, 0, 0]


def test_a_team_split_after_it_finished_explores_again() -> None:
    """A merge undone after the team reached its coverage leaves two teams that have not: both
    go back to exploring (the server does not stop on the team's earlier finish)."""
    spawn = {**SPAWN, "r3": (-7.0, 7.0, 1.2)}
    core, _ = run(40, cfg=config(("r1", "r2", "r3"), refine_on_maps=False), spawn=spawn)
    assert len(core.teams) == 1
    team = next(iter(core.teams.values()))
    stamp = core.robots["r1"].last_stamp_ns
    core.progress.finish_team(team, stamp, "coverage reached")
    assert core.finished and all(r.nav.mode == "done" for r in core.robots.values())
    last = core.merges[-1]
    pair = (sorted(last.robots_b)[0], next(r for r in team.robot_ids if r not in last.robots_b))
    core.merger.undo(team, stamp, tuple(sorted(pair)))
    assert last.undone_stamp_ns == stamp and len(core.teams) == 2
    assert not core.finished and not any(t.finished for t in core.teams.values())
    assert all(r.nav.mode != "done" and r.nav.finished_reason == "" for r in core.robots.values())


def test_a_proposal_whose_rotation_the_maps_contradict_is_refused() -> None:
    """A proposal right where the robots stand but turned 4° (sightings from afar, sharing one
    error across the line of sight): matched where they overlap, the maps turn it back by
    more than its σ allows, and the merge is refused; the true transform merges."""
    from server.rendezvous.evidence import MergeProposal

    # no merge from sightings; and no conflict check, which would see 4° here, so close to
    # both robots' starts, but not far from them, where such merges came from
    core, _ = run(60, cfg=config(min_sightings=1000, max_conflict_ratio=1.0))
    assert len(core.teams) == 2
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
    meet = core.robots["r2"].pose                             # where r2 is, in its own frame
    turn = np.array([0.0, 0.0, math.radians(4.0)])
    at_meet = compose(T_true, meet)                           # r2 in r1's frame
    # turned about r2's current place: right there, 4° off everywhere else
    T_bad = compose(compose(at_meet, turn), between(meet, np.zeros(3)))
    C = np.diag([0.02 ** 2, 0.02 ** 2, math.radians(0.8) ** 2])
    core.merger.try_merge(MergeProposal("team-r1", "team-r2", (), T_bad, C, T_bad), 1)
    assert len(core.teams) == 2 and core.tag_counters["merges_rejected"] == 1
    assert any(e.kind == "merge_rejected" and "turn" in e.message for e in core.event_log)
    # (with no sightings, a link between the start frames holds the graphs together)
    _, link = core.surgery.own_frames_link("r1", "r2", T_true, np.array([0.02, 0.02, 0.01]),
                                           "marker", 2)
    core.merger.try_merge(MergeProposal("team-r1", "team-r2", (), T_true, C, T_true), 2,
                          (link,), kind="marker")
    assert len(core.teams) == 1 and len(core.merges) == 1
    assert abs(core.merges[0].agreement["map_turn_deg"]) < 1.0


def test_a_team_whose_live_robots_are_done_finishes_without_the_one_that_vanished() -> None:
    core, _ = run(20, cfg=config(start_poses={r: list(p) for r, p in SPAWN.items()}))
    assert len(core.teams) == 1
    team = next(iter(core.teams.values()))
    stamp = core.robots["r1"].last_stamp_ns
    core.set_alive("r2", False)
    core.robots["r1"].nav.finish("no reachable frontier left")
    assert core.robots["r2"].nav.mode != "done"
    core.progress.update(stamp + 1)
    assert team.finished and core.finished
    # ... but a team with no live robot left is not taken for done
    core2, _ = run(20, cfg=config(start_poses={r: list(p) for r, p in SPAWN.items()}))
    for rid in SPAWN:
        core2.set_alive(rid, False)
    core2.progress.update(core2.robots["r1"].last_stamp_ns + 1)
    assert not core2.finished


def test_robots_that_vanished_alone_do_not_hold_back_the_end() -> None:
    """Two robots, each still alone; r2 drops out (its agent was killed) and r1 finishes: the
    exploration is over (an exit-when-done server exits), though r2's team never finished."""
    core, _ = run(20, cfg=config(enabled=False))
    assert len(core.teams) == 2
    core.set_alive("r2", False)
    assert not core.finished
    core.robots["r1"].nav.finish("no reachable frontier left")
    core.progress.update(core.robots["r1"].last_stamp_ns + 1)
    assert core.teams["team-r1"].finished and core.finished
    assert not core.teams["team-r2"].finished
    core.set_alive("r2", True)   # it came back: its team has work left
    assert not core.finished


def test_slam_does_not_see_the_teammates_bodies() -> None:
    """Beams that end on a teammate's body are left out of the robot's scan matching and map
    (a row of robots along a corridor would otherwise hold each other in place); other beams,
    and a robot alone, keep their returns."""
    core, _ = run(20, cfg=config(start_poses={r: list(p) for r, p in SPAWN.items()}))
    r1, r2 = core.robots["r1"], core.robots["r2"]
    assert r1.team_id == r2.team_id
    rel = between(r1.pose, np.array([*r2.pose[:2], 0.0]))
    bearing, dist = math.atan2(rel[1], rel[0]), math.hypot(rel[0], rel[1])
    angles = np.array([bearing, bearing + 0.02, bearing + 1.0, bearing - 1.0])
    ranges = np.array([dist - 0.13, dist - 0.1, 3.0, np.inf])
    out = core.fleet.without_teammates(r1, ranges, angles)
    assert np.isnan(out[:2]).all()                      # on r2's body: no return
    assert out[2] == 3.0 and out[3] == np.inf           # the rest as measured
    assert not np.isnan(ranges).any()                   # the navigator's scan is untouched
    core.set_alive("r2", False)                         # a vanished teammate is not filtered
    assert not np.isnan(core.fleet.without_teammates(r1, ranges, angles)).any()


def keyframe_errors(core: ServerCore, truth: dict[int, dict[str, tuple[float, float, float]]]
                    ) -> float:
    """The largest position error of any keyframe of either robot in the team frame (r1's
    first pose), against the truth at the keyframe's stamp."""
    r1_start = np.array(SPAWN["r1"])
    worst = 0.0
    for rid in SPAWN:
        sl = core.robots[rid].slam
        for kf, P in zip(sl.keyframes, sl.keyframe_poses(), strict=True):
            est, true = compose(r1_start, P), np.array(truth[kf.stamp_ns][rid])
            worst = max(worst, math.hypot(*(est[:2] - true[:2])))
    return worst


def test_sightings_leave_the_graph_once_the_maps_tie_the_robots() -> None:
    """Every sighting of one meeting is off the same way (5° in the tag's heading, 2° in
    bearing): kept in the graph beside the map matches, they hold the robots' relative pose
    off where they met while the matches pull it right, and both maps bend. Once the maps tie
    the pair, the sightings leave the graph and no more are added."""

    def biased(step: int, observer: str, d: TagDetection) -> TagDetection:
        return msgspec.structs.replace(d, yaw_rad=d.yaw_rad + math.radians(5.0),
                                       bearing_rad=d.bearing_rad + math.radians(2.0))

    truth: dict[int, dict[str, tuple[float, float, float]]] = {}
    core, _ = run(300, relabel=biased, truth=truth)
    assert len(core.merges) == 1 and len(core.teams) == 1
    team = next(iter(core.teams.values()))
    assert core.tag_counters["sightings_retired"] > 0
    assert not [ln for ln in team.links if ln.record.kind == "rendezvous"]
    assert sum(ln.record.kind == "cross" for ln in team.links) >= 3
    fg = core.robots["r1"].slam.graph.isam.getFactorsUnsafe()   # removed factors are null
    assert not [i for i in range(fg.size()) if isinstance(fg.at(i), gtsam.CustomFactor)]
    kept = keyframe_errors(core, truth)

    truth_old: dict[int, dict[str, tuple[float, float, float]]] = {}
    old, _ = run(300, relabel=biased, truth=truth_old, cfg=config(retire_sightings_after=0))
    assert old.tag_counters["sightings_retired"] == 0
    assert any(ln.record.kind == "rendezvous" for t in old.teams.values() for ln in t.links)
    bent = keyframe_errors(old, truth_old)
    assert kept <= 0.025 and bent >= 2 * kept, (kept, bent)


def test_a_team_merged_on_sightings_snapshots_and_comes_back(tmp_path: Path) -> None:
    """The server's snapshot of a team joined by tag sightings (rendezvous factors, kept in
    its graph here) reads back: same teams and merges, poses to well under a millimetre."""
    from factors.rendezvous import RecipeFactor
    from server.runtime.snapshot import Snapshots

    core, _ = run(250, cfg=config(retire_sightings_after=0))
    assert len(core.teams) == 1
    g = core.robots["r1"].slam.graph.isam.getFactorsUnsafe()
    assert any(g.exists(i) and isinstance(g.at(i), RecipeFactor) for i in range(g.size()))
    snaps = Snapshots(tmp_path)
    snaps.write(core, 7)
    loaded = snaps.load()
    assert loaded is not None and loaded[1] == 7
    back = loaded[0]
    assert sorted(back.teams) == sorted(core.teams) and len(back.merges) == len(core.merges)
    for rid, r in core.robots.items():
        assert np.allclose(back.robots[rid].slam.keyframe_poses(), r.slam.keyframe_poses(),
                           atol=1e-4)


def test_teams_whose_merge_the_maps_keep_refusing_stop_seeking_each_other() -> None:
    """Robots that keep reading each other's tags while their maps refuse the merge would
    follow each other instead of exploring: after ``refusals_to_pause`` refusals without a
    ``refusal_pause_s`` gap, sightings still count but call nobody, no approach goes on,
    and the calls come back once the latest refusal is that old, or once a team is done."""
    from server.rendezvous.evidence import MergeProposal

    core, _ = run(60, cfg=config(min_sightings=1000, max_conflict_ratio=1.0))
    r1, r2 = core.robots["r1"], core.robots["r2"]
    t = core.cfg.teams
    assert len(core.teams) == 2 and t.refusals_to_pause == 3
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
    meet = r2.pose                     # turned 4° about r2's place: the maps refuse it
    at_meet = compose(T_true, meet)
    T_bad = compose(compose(at_meet, np.array([0.0, 0.0, math.radians(4.0)])),
                    between(meet, np.zeros(3)))
    C = np.diag([0.02 ** 2, 0.02 ** 2, math.radians(0.8) ** 2])
    now = r1.last_stamp_ns
    far = TagDetection(tag_id=2, observed_robot_id="r2", range_m=3.0, bearing_rad=0.3,
                       yaw_rad=math.pi, sigma_range_m=0.05, sigma_bearing_rad=0.02,
                       sigma_yaw_rad=0.5)

    def sighting() -> None:
        r1.look.call = r2.look.call = None
        core.desk._call("r1", far)

    def refuse(stamp_ns: int) -> None:
        core.merger.try_merge(MergeProposal("team-r1", "team-r2", (), T_bad, C, T_bad),
                              stamp_ns)

    s = int(1e9)
    pause = int(t.refusal_pause_s * s)
    refuse(now - 3 * pause)                         # long ago: a count of its own
    refuse(now - pause // 2)
    refuse(now - pause // 4)                        # two in this run
    assert core.tag_counters["merges_rejected"] == 3
    assert not core.fleet.seeking_paused("team-r1", "team-r2", now)
    sighting()
    assert r1.look.call is not None and r2.look.call is not None   # still seeking
    refuse(now)                                     # three
    assert core.fleet.seeking_paused("team-r2", "team-r1", now)          # either order
    sighting()
    assert r1.look.call is None and r2.look.call is None
    assert core.tag_counters["calls_paused"] == 1
    # an approach under way is dropped, and nobody is looked for
    r1.look.approaching, r1.look.track = True, r1.pose[:2] + 1.0
    assert r1.look.active
    assert core.steering.look(r1, now * 1e-9, np.zeros((0, 2))) is None
    assert not r1.look.active
    # a clock stepped back before the latest refusal does not hold the pause for that long
    assert not core.fleet.seeking_paused("team-r1", "team-r2", now - 1)
    # a robot on its way to a meeting planned before goes on with it
    from server.fleet.model import Meeting

    r1.meeting = Meeting("go", "r2", 0, now * 1e-9 + 60.0)
    assert not core.fleet.others_paused(r1, now)
    sighting()
    assert r1.look.call is not None
    r1.meeting = None
    # a team that has finished exploring seeks the other again
    core.teams["team-r1"].finished = True
    assert not core.fleet.seeking_paused("team-r1", "team-r2", now)
    core.teams["team-r1"].finished = False
    # the refusals age: the robots seek each other again
    later = now + int(core.cfg.teams.refusal_pause_s * 1e9) + 1
    assert not core.fleet.seeking_paused("team-r1", "team-r2", later)
    r1.last_stamp_ns = r2.last_stamp_ns = later
    sighting()
    assert r1.look.call is not None and r2.look.call is not None
    # and with refusals_to_pause 0 nothing ever pauses
    core.cfg.teams.refusals_to_pause = 0
    assert not core.fleet.seeking_paused("team-r1", "team-r2", now)


def test_the_online_pose_is_kept_in_the_team_maps_frame_too(
        met: tuple[ServerCore, Simulator]) -> None:
    """After the merge, r2's poses are also recorded in r1's own map frame (the frame the
    team's map is drawn in), and they lie on the truth there; r1, the team's first robot,
    has no such rows."""
    core, sim = met
    team = core.fleet.team_of(core.robots["r2"])
    first = team.robot_ids[0]
    other = next(r for r in SPAWN if r != first)
    assert not core.robots[first].online_in
    rows = core.robots[other].online_in[first]
    merged_ns = core.merges[0].stamp_ns
    assert len(rows) > 10 and rows.stamps[0] >= merged_ns
    last = compose(np.array(SPAWN[first]), rows.values[-1])
    truth = np.array(sim.robots[other].pose)
    assert math.hypot(*(last[:2] - truth[:2])) < 0.1
    # the same pose as the robot's own-frame row, seen through its first keyframe's place
    own = core.robots[other].online.values[-1]
    T = core.robots[other].own_frame_in_team()
    np.testing.assert_allclose(compose(T, own)[:2], rows.values[-1][:2], atol=1e-6)
