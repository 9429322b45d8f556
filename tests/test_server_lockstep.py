"""The lockstep barrier: a step's messages come out in one order, whatever order they came in."""

from __future__ import annotations

import itertools
import threading
from typing import Any

import numpy as np

from schemas import Scan, TagDetections
from schemas.messages import quantise_ranges_mm
from server.runtime.inbox import Inbox
from server.runtime.lockstep import StepBarrier
from server.runtime.work import AliveWork, ScanWork, TagsWork


def scan(rid: str, stamp_ns: int) -> Scan:
    return Scan(robot_id=rid, seq=1, stamp_ns=stamp_ns, odom_pose=(0.0, 0.0, 0.0),
                angle_min_rad=0.0, angle_increment_rad=0.1, range_min_mm=50,
                range_max_mm=1000, ranges_mm=quantise_ranges_mm(np.array([0.5]), 0.05, 1.0))


def tags(rid: str, stamp_ns: int) -> TagDetections:
    return TagDetections(robot_id=rid, seq=1, stamp_ns=stamp_ns, detections=[])


class Queues:
    """The node's queues (an ``Inbox``) and its condition."""

    def __init__(self) -> None:
        self.inbox = Inbox(per_robot=50)
        self.cv = threading.Condition()

    def put(self, name: str, item: Any) -> None:
        if name.startswith("#alive:"):
            self.inbox.put_control(name, item)
        else:
            self.inbox.put(name, item)

    def arrive(self, msg: Scan | TagDetections) -> None:
        if isinstance(msg, Scan):
            self.put(msg.robot_id, ScanWork(msg, msg.stamp_ns))
        else:
            self.put(f"#tags:{msg.robot_id}", TagsWork(msg))


def taken(b: StepBarrier, q: Queues, alive: set[str]) -> list[tuple[str, int]]:
    with q.cv:
        return [(name, item.scan.stamp_ns if isinstance(item, ScanWork) else
                 item.tags.stamp_ns) for name, item in b.take(q.inbox, q.cv, alive)]


def test_a_step_comes_out_in_robot_order_whatever_the_arrival_order() -> None:
    msgs = [scan("r2", 100), tags("r1", 50), scan("r1", 100), tags("r2", 100), scan("r3", 100),
            tags("r3", 90)]
    seen = set()
    for perm in itertools.permutations(msgs):
        q = Queues()
        for m in perm:
            q.arrive(m)
        seen.add(tuple(taken(StepBarrier(5.0), q, {"r1", "r2", "r3"})))
    assert seen == {(("r1", 100), ("r2", 100), ("r3", 100), ("#tags:r1", 50),
                     ("#tags:r3", 90))}       # r2's sightings of this step wait for the next


def test_a_robot_that_misses_a_step_is_waited_for_once() -> None:
    q, b = Queues(), StepBarrier(0.05)
    q.arrive(scan("r1", 100))
    assert taken(b, q, {"r1", "r2"}) == [("r1", 100)]       # after the barrier's 50 ms
    assert b.timeouts == 1 and b.missed == {"r2"}
    q.arrive(scan("r1", 200))
    assert taken(b, q, {"r1", "r2"}) == [("r1", 200)]       # not waited for again
    assert b.timeouts == 1
    q.arrive(scan("r2", 300))
    q.arrive(scan("r1", 300))
    assert taken(b, q, {"r1", "r2"}) == [("r1", 300), ("r2", 300)]
    assert b.missed == set()                                 # back in the step


def test_a_robot_leaving_is_not_waited_for_and_its_news_comes_first() -> None:
    q, b = Queues(), StepBarrier(5.0)
    q.arrive(scan("r1", 100))
    q.put("#alive:r2", AliveWork("r2", False))
    with q.cv:
        out = b.take(q.inbox, q.cv, {"r1", "r2"})   # at once: r2 is leaving
    assert [name for name, _ in out] == ["#alive:r2", "r1"] and out[0][1].alive is False
    assert b.timeouts == 0 and len(q.inbox) == 0 and not q.inbox.control


def test_robots_joining_come_out_in_robot_order_whatever_order_their_tokens_came_in() -> None:
    """The order robots are added in gives them their graph symbols, so a fleet whose tokens
    come in another order at the start must still make the same run. One robot's own news
    keeps its order (it came, then went)."""
    for perm in itertools.permutations(["r3", "r1", "r2"]):
        q, b = Queues(), StepBarrier(5.0)
        for rid in perm:
            q.put(f"#alive:{rid}", AliveWork(rid, True))
        q.put("#alive:r1", AliveWork("r1", False))
        for rid in ("r2", "r3"):
            q.arrive(scan(rid, 100))
        with q.cv:
            out = b.take(q.inbox, q.cv, {"r2", "r3"})
        assert [(name, item.alive) for name, item in out[:4]] == [
            ("#alive:r1", True), ("#alive:r1", False), ("#alive:r2", True), ("#alive:r3", True)]
