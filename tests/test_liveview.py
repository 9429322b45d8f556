"""Transforms between two teams' maps checked against what the robots see now
(server.rendezvous.liveview): a disc seen empty, and a real core whose robots look where a
wrong transform puts the other robot — and where the right one does."""

from __future__ import annotations

import math

import numpy as np

from server.core import ServerCore
from server.fleet.model import LiveView
from server.rendezvous import liveview
from server.rendezvous.liveview import seen_empty
from server.rendezvous.matchdesk import HypothesisEntry
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from tests.test_cluster_handover import step_messages
from tests.test_meetings import SPAWN, T_TRUE, _NoTags
from tests.test_team_merge import WORLD, config


def _ring(r_m: float = 5.0, n: int = 400) -> LiveView:
    """A robot at the origin, facing +x, in a round room of radius ``r_m``."""
    angles = np.linspace(-math.pi, math.pi, n, endpoint=False)
    return LiveView(0, "team-a", np.zeros(3), np.full(n, r_m), angles)


def test_a_disc_with_every_beam_through_it_is_seen_empty() -> None:
    view = _ring()
    assert seen_empty(view, np.array([3.0, 0.0]))
    assert seen_empty(view, np.array([0.0, -3.0]))          # any bearing


def test_a_robot_in_the_disc_a_wall_in_it_or_no_return_tell_nothing() -> None:
    view = _ring()
    body = view.ranges.copy()
    k = int(np.argmin(np.abs(view.angles - math.atan2(0.4, 3.0))))
    body[k] = 3.3                                            # one beam stops on a body
    assert not seen_empty(LiveView(0, "team-a", np.zeros(3), body, view.angles),
                          np.array([3.0, 0.4]))
    assert not seen_empty(view, np.array([4.5, 0.0]))        # the room's wall lies in it
    gap = view.ranges.copy()
    gap[np.abs(view.angles) < 0.05] = np.nan                 # beams not read
    assert not seen_empty(LiveView(0, "team-a", np.zeros(3), gap, view.angles),
                          np.array([3.0, 0.0]))
    assert not seen_empty(_ring(20.0), np.array([9.0, 0.0]))  # too far to tell
    assert seen_empty(_ring(math.inf), np.array([3.0, 0.0]))  # no return in range: open
    short = _ring(math.inf)
    short.range_max_m = 3.0                                   # a depth camera's 3 m
    assert not seen_empty(short, np.array([2.5, 0.0]))        # the disc reaches past it
    assert seen_empty(short, np.array([1.5, 0.0]))            # within it: open
    assert not seen_empty(view, np.array([0.8, 0.0]))         # the robot itself is in it


def test_the_view_is_taken_in_the_robots_frame() -> None:
    view = _ring()
    view.pose = np.array([10.0, 5.0, math.pi / 2])           # at (10, 5), facing +y
    view.ranges[np.abs(view.angles) < 0.3] = 2.0             # a wall 2 m ahead of it
    assert not seen_empty(view, np.array([10.0, 8.0]))       # behind that wall: unseen
    assert seen_empty(view, np.array([7.0, 5.0]))            # to its left: open


def _run(T_ab: np.ndarray, steps: int) -> tuple[ServerCore, HypothesisEntry]:
    """Two robots of two teams 2.2 m apart in one room, a hypothesis ``T_ab`` logged, the
    desk ticked at every scan."""
    sim = Simulator(load_world(WORLD), SPAWN, SimParams(), seed=1)
    core = ServerCore(config(map_match=False))
    e = HypothesisEntry(0, 0, "team-r1", "team-r2", "r1", "r2", T_ab, 4, 2, 2, 3, 0.99)
    core.matcher.log.append(e)
    for _ in range(steps):
        obs = sim.sense()
        scans, _ = step_messages(sim, _NoTags(), obs)
        for scan in scans.values():
            core.on_scan(scan)
        core.matcher.tick(core.robots["r1"].last_stamp_ns)
        sim.advance()
    return core, e


def test_a_transform_that_puts_the_other_robot_on_open_floor_is_refuted() -> None:
    # r2's frame placed 2.5 m off, where r1 sees the room's open floor (-8, 6.5)
    wrong = T_TRUE + np.array([-2.0, -1.5, 0.0])
    core, e = _run(wrong, 25)
    assert e.status == "refuted" and "saw open floor" in e.reason
    assert core.tag_counters["map_refuted_by_view"] == 1
    # refuted after the looks it takes, not at the first one
    assert core.matcher.looks.looks == {}


def test_the_right_transform_is_never_refuted_by_a_look() -> None:
    core, e = _run(T_TRUE, 40)
    assert e.status == "pending"
    assert core.tag_counters["map_refuted_by_view"] == 0
    # nor one 0.7 m off (a meeting's transform may be this rough)
    core, e = _run(T_TRUE + np.array([0.5, 0.5, 0.0]), 40)
    assert e.status == "pending"


def test_looks_needed_before_a_transform_is_refuted() -> None:
    assert liveview.LOOKS >= 2 and liveview.LOOKS_SPAN_S > 0
    wrong = T_TRUE + np.array([-2.0, -1.5, 0.0])
    _, e = _run(wrong, 5)                     # 0.5 s of looks: not yet
    assert e.status == "pending"


def test_the_latest_scan_is_not_kept_in_a_snapshot() -> None:
    """A robot's latest scan is the moment's: a snapshot (a pickle of the core) leaves it
    out, and the next scan after a restart gives it again."""
    import pickle

    core, _ = _run(T_TRUE, 3)
    r1 = core.robots["r1"]
    assert r1.view is not None and len(r1.view.ranges) > 0
    back = pickle.loads(pickle.dumps(r1))
    assert back.view is None and back.robot_id == "r1"
    assert np.array_equal(back.pose, r1.pose)
