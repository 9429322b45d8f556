"""The worker's queues (``server.runtime.inbox``): robots take turns, trusted robots first, control
items ahead of all, and a robot's backlog is bounded."""

from __future__ import annotations

from server.runtime.inbox import NEWCOMER, TRUSTED, Inbox


def drain(inbox: Inbox) -> list[str]:
    out = []
    while (item := inbox.take()) is not None:
        out.append(item[0])
    return out


def test_robots_take_turns_whatever_their_backlog() -> None:
    inbox = Inbox(per_robot=50)
    for k in range(40):
        inbox.put("busy", k)
    inbox.put("r1", "a")
    inbox.put("r2", "b")
    inbox.put("r1", "c")
    order = drain(inbox)
    assert order[:5] == ["busy", "r1", "r2", "busy", "r1"]
    assert len(order) == 43 and len(inbox) == 0 and inbox.queues == {}


def test_trusted_robots_are_served_before_a_thousand_newcomers() -> None:
    inbox = Inbox(per_robot=50)
    for i in range(1000):
        for k in range(3):
            inbox.put(f"f{i}", k, NEWCOMER)
    for k in range(5):
        inbox.put("r1", k, TRUSTED)
    inbox.put_control("#alive:r2", True)
    order = drain(inbox)
    assert order[:6] == ["#alive:r2", "r1", "r1", "r1", "r1", "r1"]
    assert len(order) == 3006


def test_a_robot_behind_loses_its_oldest_messages_only() -> None:
    inbox = Inbox(per_robot=3)
    for k in range(5):
        inbox.put("r1", k)
    assert inbox.dropped == {"r1": 2} and len(inbox) == 3
    assert [inbox.take() for _ in range(3)] == [("r1", 2), ("r1", 3), ("r1", 4)]
    assert inbox.take() is None


def test_a_step_taken_by_name_leaves_the_turns_consistent() -> None:
    inbox = Inbox(per_robot=10)
    inbox.put("r1", 1)
    inbox.put("r2", 2)
    inbox.put_control("#alive:r1", True)
    assert inbox.take_named("r1") == 1 and inbox.take_named("#alive:r1") is True
    assert not inbox.control and len(inbox) == 1
    assert drain(inbox) == ["r2"]
