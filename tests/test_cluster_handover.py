"""A team moves whole between two server cores: the robots meet in the small house while each
is served by its own worker's core; at the first sighting one worker gives its team to the
other (packed to bytes and back, as it travels), and the merge that follows is as accurate as
in one core. A merged team moved on afterwards keeps its joint graph and its merge record."""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from bench.support.fleet import RoomRobot
from bench.support.mission import scan_of
from robot_agent.aruco import TagDetector
from schemas import Scan, TagDetection, TagDetections, VelocityCommand, keys
from schemas.bus import Bus, free_local_endpoint
from schemas.se2 import between, compose, pose_distance
from schemas.tags import CameraMount, TagLayout
from server.config import ServerConfig
from server.core import ServerCore
from server.runtime import handover
from server.runtime.cluster import _rank
from server.runtime.journal import JournalWriter, replay
from server.runtime.node import ServerNode
from sim.loader import load_world
from sim.simulator import SimParams, Simulator
from tests.test_team_merge import SPAWN, WORLD, config
from tests.waiting import within

#: runs closed-loop missions or SLAM over whole recordings: `make test-fast` leaves it out
pytestmark = pytest.mark.slow


def worker_config(index: int) -> ServerConfig:
    return ServerConfig.model_validate({**config().model_dump(), "cluster": {"worker": index}})


def step_messages(sim: Simulator, detector: TagDetector, obs) -> tuple[dict[str, Scan],  # type: ignore[no-untyped-def]
                                                                        list[TagDetections]]:
    """A simulated step's scans (by robot) and tag messages, as agents would send them."""
    scans = {rid: scan_of(sim, obs, rid) for rid in sim.robots}
    tags = []
    for rid, frame in obs.frames.items():
        found = detector.detect(frame.image, sim.p.camera.camera.K, rid)
        dets = [TagDetection(tag_id=s.tag_id, observed_robot_id=s.robot_id, range_m=s.range_m,
                             bearing_rad=s.bearing_rad, yaw_rad=s.yaw_rad,
                             sigma_range_m=s.sigma_range_m,
                             sigma_bearing_rad=s.sigma_bearing_rad,
                             sigma_yaw_rad=s.sigma_yaw_rad) for s in found.sightings]
        if dets:
            tags.append(TagDetections(robot_id=rid, seq=obs.step + 1, stamp_ns=obs.stamp_ns,
                                      detections=dets))
    return scans, tags


class TwoWorkers:
    """r1 served by worker 0's core, r2 by worker 1's, until a team moves."""

    def __init__(self) -> None:
        self.sim = Simulator(load_world(WORLD), SPAWN, SimParams(), seed=3)
        self.cores = {0: ServerCore(worker_config(0)), 1: ServerCore(worker_config(1))}
        self.owner = {"r1": 0, "r2": 1}
        self.detector = TagDetector(TagLayout(), CameraMount())
        self.moved: list[tuple[int, int, int]] = []   # (step, from, to)
        self.parcel_bytes = 0

    def move(self, robot_id: str, to: int, step: int) -> None:
        src = self.owner[robot_id]
        parcel = handover.release(self.cores[src], robot_id)
        assert parcel is not None
        data = handover.pack(parcel)
        self.parcel_bytes = len(data)
        handover.adopt(self.cores[to], handover.unpack(data))
        for rid in parcel.robot_ids:
            self.owner[rid] = to
        self.moved.append((step, src, to))

    def run(self, steps: int) -> None:
        for _ in range(steps):
            obs = self.sim.sense()
            scans, tags = step_messages(self.sim, self.detector, obs)
            for rid, scan in scans.items():
                cmd = self.cores[self.owner[rid]].on_scan(scan)
                self.sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
            for msg in tags:
                seen = {d.observed_robot_id for d in msg.detections}
                for other in seen & set(self.owner):
                    a, b = self.owner[msg.robot_id], self.owner[other]
                    if a != b:   # the lower-numbered worker takes the other's team
                        self.move(msg.robot_id if a > b else other, min(a, b), obs.step)
                self.cores[self.owner[msg.robot_id]].on_tags(msg)
            self.sim.advance()


@pytest.fixture(scope="module")
def workers() -> TwoWorkers:
    w = TwoWorkers()
    w.run(250)
    return w


def test_the_team_moves_at_the_first_sighting_and_merges_there(workers: TwoWorkers) -> None:
    assert len(workers.moved) == 1 and workers.moved[0][1:] == (1, 0)
    core, left = workers.cores[0], workers.cores[1]
    assert not left.robots and not left.teams      # nothing of r2 stays behind
    assert len(core.merges) == 1 and len(core.teams) == 1
    assert core.robots["r1"].slam.graph is core.robots["r2"].slam.graph
    assert any(e.kind == "robot_joined" and "moved here" in e.message for e in core.event_log)


def test_the_moved_robots_have_keys_of_their_own(workers: TwoWorkers) -> None:
    core = workers.cores[0]
    spaces = {(core.robots[r].slam.trajectory.robot_char, core.robots[r].slam.trajectory.block)
              for r in SPAWN}
    assert len(spaces) == 2    # worker 0's first robot and worker 1's first robot


def test_the_merge_is_as_accurate_as_in_one_core(workers: TwoWorkers) -> None:
    m = workers.cores[0].merges[0]
    T_true = between(np.array(SPAWN["r1"]), np.array(SPAWN["r2"]))
    err = pose_distance(between(T_true, m.T_joint))
    assert err[0] <= 0.05 and err[1] <= math.radians(1.0)
    r1_start = np.array(SPAWN["r1"])
    for rid in SPAWN:
        truth = np.array(workers.sim.robots[rid].pose)
        est = compose(r1_start, workers.cores[0].robots[rid].pose)
        assert math.hypot(*(est[:2] - truth[:2])) < 0.1


def test_a_merged_team_moves_on_with_its_graph_and_merge(workers: TwoWorkers) -> None:
    keyframes = {r: len(workers.cores[0].robots[r].slam.keyframes) for r in SPAWN}
    workers.move("r1", 1, -1)
    core = workers.cores[1]
    assert not workers.cores[0].robots and not workers.cores[0].merges
    assert len(core.merges) == 1 and core.retired_teams
    assert {r: len(core.robots[r].slam.keyframes) for r in SPAWN} == keyframes
    workers.run(60)       # and goes on exploring there, on the truth
    r1_start = np.array(SPAWN["r1"])
    for rid in SPAWN:
        truth = np.array(workers.sim.robots[rid].pose)
        est = compose(r1_start, core.robots[rid].pose)
        assert math.hypot(*(est[:2] - truth[:2])) < 0.1
    assert len(core.teams) == 1 and not workers.cores[0].robots


def test_a_parcel_from_other_code_or_damaged_is_refused() -> None:
    w = TwoWorkers()
    w.run(3)
    parcel = handover.release(w.cores[w.owner["r2"]], "r2")
    assert parcel is not None
    data = handover.pack(parcel)
    with pytest.raises(handover.ParcelError, match="written by mrslam"):
        handover.unpack(handover.MAGIC + b"0.0.0-other\n" + data.split(b"\n", 2)[2])
    with pytest.raises(handover.ParcelError, match="unreadable"):
        handover.unpack(data[:-50])
    with pytest.raises(handover.ParcelError, match="not a team parcel"):
        handover.unpack(b"hello")


# -- two worker nodes over Zenoh on loopback ----------------------------------------------------
# r1 ranks for worker 1 and r7 for worker 0 (rendezvous hashing over workers {0, 1})
BUS_SPAWN = {"r1": SPAWN["r1"], "r7": SPAWN["r2"]}


@dataclass(frozen=True)
class Gate:
    """Holds a worker's thread until ``event`` is set."""

    event: threading.Event


class Robots:
    """The robots' side of the wire: liveliness tokens, scans and tags out, commands in."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.cmds: dict[str, dict[int, VelocityCommand]] = {rid: {} for rid in BUS_SPAWN}
        for rid in BUS_SPAWN:
            bus.declare_alive(keys.robot_alive(rid))
            bus.subscribe(keys.robot_cmd_vel(rid), VelocityCommand, self._on_cmd)

    def _on_cmd(self, _key: str, cmd: VelocityCommand) -> None:
        self.cmds[cmd.robot_id][cmd.stamp_ns] = cmd


@pytest.mark.e2e
@pytest.mark.parametrize("busy_at", [0, 1])
def test_two_worker_nodes_hand_a_team_over_on_the_bus(tmp_path: Path, busy_at: int,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    assert [max((0, 1), key=lambda w: _rank(r, w)) for r in BUS_SPAWN] == [1, 0]
    caplog.set_level(logging.INFO, logger="server.runtime.moves")
    endpoint = free_local_endpoint()
    base = {**config(("r1", "r7")).model_dump(), "clock": {"source": "stamps"}}
    sim = Simulator(load_world(WORLD), BUS_SPAWN, SimParams(), seed=3)
    detector = TagDetector(TagLayout(), CameraMount())
    with Bus.open("router", listen=[endpoint]), \
            Bus.open("client", connect=[endpoint]) as robot_bus:
        nodes = {}
        for w in (0, 1):
            cfg = ServerConfig.model_validate({**base, "cluster": {"worker": w},
                                               "bus": {"connect": [endpoint]}})
            bus = Bus.open("client", connect=[endpoint])
            nodes[w] = ServerNode(bus, cfg, journal=JournalWriter(tmp_path / f"w{w}"))
            nodes[w].start()
        robots = Robots(robot_bus)
        assert within(lambda: all(n.cluster is not None and n.cluster.workers == {0, 1}
                                  for n in nodes.values()), 10.0)
        unanswered = 0
        # the giver is busy when the team is asked for: r1's scan of that step waits in its
        # queue (busy_at=1: the asker had let that scan pass by, as another worker's), or its
        # first scan does (busy_at=0: it has not mapped r1 yet)
        gate = threading.Event()
        nodes[1]._handlers[Gate] = lambda g: g.event.wait(5.0)
        early: list[TagDetections] = []    # sightings before the busy step go with it
        try:
            for step in range(200):
                obs = sim.sense()
                scans, tags = step_messages(sim, detector, obs)
                if step < busy_at:
                    early, tags = early + tags, []
                if step == busy_at:
                    nodes[1]._queue_control("#gate:", Gate(gate))
                for rid, scan in scans.items():
                    robot_bus.publish(keys.robot_scan(rid), scan, block=True)
                if step == busy_at:
                    # (once worker 0 knows who serves r1: then its sightings ask for it)
                    assert within(lambda: nodes[0].cluster.owner_of("r1") == 1, 5.0)
                    for msg in early + tags:
                        robot_bus.publish(keys.robot_tags(msg.robot_id), msg, block=True)
                    tags = []
                    time.sleep(0.5)
                    gate.set()
                stamp = obs.stamp_ns
                if not within(lambda s=stamp: all(s in robots.cmds[r] for r in BUS_SPAWN), 5.0):
                    unanswered += 1
                for rid in BUS_SPAWN:
                    cmd = robots.cmds[rid].get(stamp)
                    if cmd is not None:
                        sim.set_command(rid, cmd.v_mps, cmd.omega_rps)
                for msg in tags:
                    robot_bus.publish(keys.robot_tags(msg.robot_id), msg, block=True)
                sim.advance()
            merged = within(lambda: len(nodes[0].core.merges) == 1, 10.0)
        finally:
            summaries = {w: n.summary() for w, n in nodes.items()}
            for n in nodes.values():
                n.stop()
                n.bus.close()
    # worker 0 asked worker 1 for r1's team, got it and merged it with r7's
    c0, c1 = summaries[0]["cluster"], summaries[1]["cluster"]
    if busy_at == 0:       # nothing to give: worker 1 let r1 go, worker 0 mapped it afresh
        assert c0["asked"] == 1 and c0["not_adopted"] == 1 and c1["let_go"] == 1
        assert "given" not in c1
        # the usual start of a split server, not a team lost: no warning for it
        assert any("mapped here from its first scans" in r.getMessage()
                   for r in caplog.records if r.levelno == logging.INFO)
        assert not [r.getMessage() for r in caplog.records
                    if r.name == "server.runtime.moves" and r.levelno >= logging.WARNING]
    else:
        assert c0["asked"] == 1 and c0["adopted"] == 1 and c1["given"] == 1
    assert c0["robots_served"] == ["r1", "r7"] and c1["robots_served"] == []
    assert gate.is_set() and merged and not nodes[1].core.robots
    # each worker's commands are no stranger's to the other
    assert nodes[0].foreign_commands == nodes[1].foreign_commands == {}
    core = nodes[0].core
    assert core.robots["r1"].slam.graph is core.robots["r7"].slam.graph
    # every scan was taken by one worker or the other, once: none lost in the move
    assert core.robots["r1"].scans == core.robots["r7"].scans == 200
    assert unanswered <= 2
    m = core.merges[0]
    T_true = between(np.array(BUS_SPAWN["r7"]), np.array(BUS_SPAWN["r1"]))
    if m.team_id != "team-r7":
        T_true = between(np.array(BUS_SPAWN["r1"]), np.array(BUS_SPAWN["r7"]))
    err = pose_distance(between(T_true, m.T_joint))
    assert err[0] <= 0.05 and err[1] <= math.radians(1.0)
    # each worker's journal gives back its own state: the team moved, and where to
    for w, robots_there in ((0, {"r1", "r7"}), (1, set())):
        again = ServerCore(nodes[w].cfg)
        report = replay(again, tmp_path / f"w{w}")
        assert report.unreadable == 0
        assert set(again.robots) == robots_there
    assert len(again.merges) == 0


def worker_node(endpoint: str, w: int, journal: Path | None = None,
                core: ServerCore | None = None, first: int = 0, **cluster: float) -> ServerNode:
    """Worker ``w`` as a started node on its own client session (journaled in ``journal``)."""
    cfg = ServerConfig.model_validate({"cluster": {"worker": w, **cluster},
                                       "bus": {"connect": [endpoint]}})
    n = ServerNode(Bus.open("client", connect=[endpoint]), cfg, core=core,
                   journal=None if journal is None else JournalWriter(journal,
                                                                      first_sequence=first))
    n.start()
    return n


def served(n: ServerNode) -> list[str]:
    assert n.cluster is not None
    return n.cluster.summary()["robots_served"]


def two_workers_serving(endpoint: str, w0: ServerNode, w1: ServerNode, scans: int
                        ) -> list[RoomRobot]:
    """Robots r1 and r2 (both ranked for worker 1) streaming, once worker 1 serves them and
    has mapped ``scans`` of each."""
    assert within(lambda: w0.cluster is not None and w0.cluster.workers == {0, 1}, 10)
    robots = [RoomRobot(endpoint, r).start() for r in ("r1", "r2")]
    assert within(lambda: served(w1) == ["r1", "r2"] and all(
        r in w1.core.robots and w1.core.robots[r].scans > scans for r in ("r1", "r2")), 20.0)
    return robots


@pytest.mark.e2e
def test_a_vanished_workers_robots_wait_for_it_then_go_to_another(tmp_path: Path) -> None:
    """Worker 1 dies: its robots are not taken at once; restarted on its journal within the
    timeout, it serves them again with their maps. Dead for longer, worker 0 takes them."""
    assert all(max((0, 1), key=lambda w: _rank(r, w)) == 1 for r in ("r1", "r2"))
    endpoint = free_local_endpoint()

    def node(w: int, core: ServerCore | None = None, first: int = 0) -> ServerNode:
        return worker_node(endpoint, w, tmp_path / f"w{w}", core, first, handover_timeout_s=3.0)

    with Bus.open("router", listen=[endpoint]):
        w0, w1 = node(0), node(1)
        robots: list[RoomRobot] = []
        try:
            robots = two_workers_serving(endpoint, w0, w1, 20)
            assert served(w0) == []
            # worker 1 is killed (its session gone at once, as a killed process's)
            w1.bus.close()
            w1.stop()
            scans_before = w1.core.robots["r1"].scans
            assert within(lambda: w0.cluster is not None and w0.cluster.workers == {0}, 5.0)
            time.sleep(1.0)
            assert served(w0) == []           # waiting for worker 1 to come back
            # ... and it comes back on its journal, with the robots' maps
            core = ServerCore(w1.cfg)
            report = replay(core, tmp_path / "w1")
            assert core.robots["r1"].scans >= scans_before - 15
            w1 = node(1, core, report.last_sequence + 1)
            assert within(lambda: w1.core.robots["r1"].scans > scans_before + 10, 10.0)
            assert served(w1) == ["r1", "r2"] and served(w0) == []
            # killed again and gone for good: worker 0 serves the robots after the timeout
            w1.bus.close()
            w1.stop()
            t_dead = time.monotonic()
            assert within(lambda: served(w0) == ["r1", "r2"], 10.0)
            assert time.monotonic() - t_dead >= 2.5
            assert within(lambda: all(r in w0.core.robots and w0.core.robots[r].scans > 5
                                      for r in ("r1", "r2")), 10.0)
        finally:
            for r in robots:
                r.close()
            for n in (w0, w1):
                n.stop()
                n.bus.close()


@pytest.mark.e2e
def test_a_worker_stopping_on_purpose_hands_its_teams_on_with_their_maps(
        tmp_path: Path) -> None:
    endpoint = free_local_endpoint()
    with Bus.open("router", listen=[endpoint]):
        w0, w1 = worker_node(endpoint, 0), worker_node(endpoint, 1)
        robots: list[RoomRobot] = []
        try:
            robots = two_workers_serving(endpoint, w0, w1, 30)
            scans = w1.core.robots["r1"].scans
            t0 = time.monotonic()
            assert w1.leave(10.0) == []
            assert time.monotonic() - t0 < 5.0
            assert served(w0) == ["r1", "r2"]
            assert within(lambda: w0.core.robots["r1"].scans > scans, 5.0)   # its map, on
            # (the last team may still be going into worker 0's core as the leaver stops)
            assert within(lambda: w0.cluster is not None and
                          w0.cluster.counters["adopted"] == 2, 5.0)
        finally:
            for r in robots:
                r.close()
            for n in (w0, w1):
                n.stop()
                n.bus.close()
