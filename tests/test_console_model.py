"""The console's model and its pages' queues: what a page is sent, and that a slow page can
hold only a bounded amount, newest first."""

from __future__ import annotations

import itertools
import json
import zlib

import numpy as np

from schemas import Event, MapUpdate, RobotEstimate, RobotStates, TeamCoverage
from server.console.clients import MAX_WAITING, PageQueue, Pages, encode
from server.console.model import MAX_COVERAGE, ConsoleModel, Frame


def states(t_s: float, poses: dict[str, tuple[float, float, str]],
           coverage: dict[str, float]) -> RobotStates:
    return RobotStates(seq=1, stamp_ns=int(t_s * 1e9), robots=[
        RobotEstimate(robot_id=rid, team_id=team, pose=(x, y, 0.0), mode="exploring",
                      pose_sigma=(0.01, 0.02, 0.003))
        for rid, (x, y, team) in poses.items()],
        teams=[TeamCoverage(team_id=t, robot_ids=[r for r, p in poses.items() if p[2] == t],
                            coverage=c, explored_m2=10 * c) for t, c in coverage.items()])


def test_a_map_goes_to_the_page_still_compressed_and_decodes_back() -> None:
    grid = np.full((30, 40), -1, np.int8)
    grid[5:20, 5:30] = 0
    grid[10, 5:30] = 100
    msg = MapUpdate.from_grid(grid, team_id="team-r1", seq=1, stamp_ns=2_000_000_000,
                              robot_ids=["r1"], resolution_m=0.05, origin=(-1.0, -2.0, 0.0))
    m = ConsoleModel()
    frame = m.on_map(msg, seen_wall=123.0)
    assert frame.kind == "map" and frame.slot == "map:team-r1"
    data = json.loads(encode(frame).decode().split("data: ", 1)[1])
    import base64

    cells = np.frombuffer(zlib.decompress(base64.b64decode(data["cells_zlib_b64"])), np.int8)
    assert np.array_equal(cells.reshape(30, 40), grid)
    assert data["origin"][:2] == [-1.0, -2.0] and data["seen_wall_ms"] == 123_000.0


def test_trails_restart_when_a_merge_moves_a_robot_into_another_frame() -> None:
    m = ConsoleModel()
    for k in range(10):
        m.on_robots(states(k, {"r1": (0.1 * k, 0, "team-r1"), "r2": (5, 0.2 * k, "team-r2")},
                           {"team-r1": 0.1, "team-r2": 0.1}), 0.0)
    assert len(m.trails["r1"]) == 10 and len(m.trails["r2"]) == 10
    m.on_map(MapUpdate.from_grid(np.zeros((2, 2), np.int8), team_id="team-r2", seq=1,
                                 stamp_ns=0, robot_ids=["r2"], resolution_m=0.1,
                                 origin=(0.0, 0.0, 0.0)), 0.0)
    frame = m.on_robots(states(11, {"r1": (1.0, 0, "team-r1"), "r2": (3, 3, "team-r1")},
                               {"team-r1": 0.3}), 0.0)
    assert m.trails["r2"] == [[3.0, 3.0]]            # started afresh in the new frame
    assert "team-r2" not in m.maps                   # a merged-away team has no map now
    assert [t["team_id"] for t in frame.data["teams"]] == ["team-r1"]
    assert m.robots["r2"]["sigma"] == [0.01, 0.02, 0.003]


def test_series_stay_bounded() -> None:
    m = ConsoleModel()
    for k in range(3 * MAX_COVERAGE):
        m.on_robots(states(k, {"r1": (0.1 * k, 0, "t")}, {"t": k / (3 * MAX_COVERAGE)}), 0.0)
    series = m.coverage["t"]
    assert len(series) <= MAX_COVERAGE + 1
    assert series[0][0] == 0 and series[-1][0] == 3 * MAX_COVERAGE - 1   # both ends kept
    assert all(a[0] < b[0] for a, b in itertools.pairwise(series))


def test_health_gives_each_robots_rate_and_what_it_lost() -> None:
    m = ConsoleModel()
    for k in range(10):                 # r1: 10 scans a second; r2: silent since 96 s
        m.on_counts({"r1": 10 * k, "r2": 5}, 95.0 + k)
    f = m.health_frame({"r1": 3}, {"stop_all": True}, {"pages": 1}, now_wall=104.5)
    r1, r2 = f.data["robots"]["r1"], f.data["robots"]["r2"]
    assert r1["scan_rate_hz"] == 10.0 and r1["dropped_scans"] == 3 and r1["scans"] == 90
    assert r1["last_seen_s_ago"] == 0.5
    assert r2["scan_rate_hz"] == 0.0 and r2["last_seen_s_ago"] == 9.5
    assert f.data["orders"] == {"stop_all": True}
    # the rate is over the last few seconds only
    for k in range(10, 20):
        m.on_counts({"r1": 90 + 2 * (k - 9), "r2": 5}, 95.0 + k)
    r1 = m.health_frame({}, {}, {}, now_wall=115.0).data["robots"]["r1"]
    assert r1["scan_rate_hz"] == 2.0


def test_events_and_the_snapshot_a_new_page_gets() -> None:
    m = ConsoleModel()
    for k in range(400):
        m.on_event(Event(kind="merge" if k % 2 else "operator", seq=k, stamp_ns=k,
                         message=f"e{k}"))
    snap = m.snapshot(m.health_frame({}, {}, {}, now_wall=0.0))
    assert len(snap.data["events"]) == 300 and snap.data["events"][-1]["message"] == "e399"
    json.dumps(snap.data)


def test_a_slow_page_keeps_only_the_newest_of_each_slot_and_bounded_events() -> None:
    q = PageQueue()
    for k in range(50):
        q.put("map:a", f"a{k}".encode())
        q.put("robots", f"r{k}".encode())
    for k in range(MAX_WAITING + 40):
        q.put(None, f"e{k}".encode())
    got = q.take(0.0)
    assert got[-2:] == [b"a49", b"r49"]
    assert got[0] == b"e40" and len(got) == MAX_WAITING + 2
    assert q.dropped == 2 * 49 + 40
    assert q.take(0.01) == []


def test_pages_are_limited_and_each_gets_every_frame() -> None:
    pages = Pages(limit=3)
    qs = [pages.open() for _ in range(3)]
    assert pages.open() is None
    pages.send(Frame("event", {"x": 1}))
    assert all(q is not None and q.take(0.0) == [b'event: event\ndata: {"x":1}\n\n'] for q in qs)
    assert qs[0] is not None
    pages.close(qs[0])
    assert pages.open() is not None and pages.counters()["pages"] == 3


def test_the_health_frame_says_when_the_state_is_not_written() -> None:
    state = {"writing": False, "failures": 3, "not_journaled": 120,
             "last_error": "journal: [Errno 28] No space left on device"}
    frame = ConsoleModel().health_frame({}, {}, {}, now_wall=0.0, state=state)
    assert frame.data["state"] == state
