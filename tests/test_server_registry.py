"""Admission of robots and messages: unknown robots, spoofed keys, stamps out of order."""

from __future__ import annotations

import pytest

from server.registry import Refused, RobotRegistry


def test_out_of_order_and_duplicate_stamps_are_refused_per_stream() -> None:
    reg = RobotRegistry()
    reg.admit("r1", "r1", "scan", 100)
    reg.admit("r1", "r1", "tags", 50)  # another stream keeps its own order
    for stamp in (100, 99):
        with pytest.raises(Refused) as err:
            reg.admit("r1", "r1", "scan", stamp)
        assert err.value.reason == "out-of-order"
    reg.admit("r1", "r1", "scan", 101)
    c = reg.counters()["r1"]
    assert c["accepted_scan"] == 2 and c["refused_out-of-order"] == 2 and c["accepted_tags"] == 1


def test_key_must_name_the_same_robot_as_the_message() -> None:
    reg = RobotRegistry()
    with pytest.raises(Refused) as err:
        reg.admit("r2", "r1", "scan", 1)
    assert err.value.reason == "key-mismatch"
    assert "r1" not in reg.robots  # nothing was accepted from it


def test_allowlist_refuses_unknown_robots_and_their_liveliness() -> None:
    reg = RobotRegistry(["r1"])
    with pytest.raises(Refused) as err:
        reg.admit("r9", "r9", "scan", 1)
    assert err.value.reason == "unknown-robot"
    assert reg.counters()["r9"]["refused_unknown-robot"] == 1
    assert reg.set_alive("r9", True) is False
    assert reg.set_alive("r1", True) is True
    assert reg.set_alive("r1", True) is False
    assert reg.set_alive("r1", False) is True
