"""Admission of robots and messages: unknown robots, spoofed keys, stamps out of order, clocks
that step, newcomers on probation, robots that go silent."""

from __future__ import annotations

import logging

import pytest

from server.runtime.registry import AdmissionPolicy, Refused, RobotRegistry

S = 1_000_000_000  # one second [ns]
T0 = 1_800_000_000 * S  # the server's clock at the start of these tests


def admitted(reg: RobotRegistry, rid: str) -> RobotRegistry:
    reg.set_alive(rid, True, T0)
    return reg


def test_out_of_order_and_duplicate_stamps_are_refused_per_stream() -> None:
    reg = admitted(RobotRegistry(), "r1")
    assert reg.admit("r1", "r1", "scan", T0 + 100, T0) == [("scan", T0 + 100, None)]
    reg.admit("r1", "r1", "tags", T0 + 50, T0)  # another stream keeps its own order
    for stamp in (T0 + 100, T0 + 99):
        with pytest.raises(Refused) as err:
            reg.admit("r1", "r1", "scan", stamp, T0)
        assert err.value.reason == "out-of-order"
    reg.admit("r1", "r1", "scan", T0 + 101, T0)
    c = reg.counters()["r1"]
    assert c["accepted_scan"] == 2 and c["refused_out-of-order"] == 2 and c["accepted_tags"] == 1
    assert "clock_steps" not in c   # repeats and reordering are not a step of the clock


def test_key_must_name_the_same_robot_as_the_message() -> None:
    reg = RobotRegistry()
    with pytest.raises(Refused) as err:
        reg.admit("r2", "r1", "scan", T0, T0)
    assert err.value.reason == "key-mismatch"
    assert "r1" not in reg.robots  # nothing was accepted from it


def test_allowlist_refuses_unknown_robots_and_their_liveliness() -> None:
    reg = RobotRegistry(AdmissionPolicy(allowed=frozenset({"r1"})))
    with pytest.raises(Refused) as err:
        reg.admit("r9", "r9", "scan", T0, T0)
    assert err.value.reason == "unknown-robot"
    assert reg.counters()["r9"]["refused_unknown-robot"] == 1
    assert reg.set_alive("r9", True, T0) == (False, [])
    assert "r9" not in reg.robots
    assert reg.set_alive("r1", True, T0)[0] is True
    assert reg.set_alive("r1", True, T0)[0] is False
    assert reg.set_alive("r1", False, T0)[0] is True


def test_a_newcomer_is_held_until_its_token_or_enough_messages_then_released_in_order() -> None:
    reg = RobotRegistry(AdmissionPolicy(probation=3))
    assert reg.admit("r1", "r1", "scan", T0 + 1, T0, "a") == []
    assert reg.admit("r1", "r1", "tags", T0 + 2, T0, "b") == []
    assert reg.set_alive("r1", True, T0) == (True, [("scan", T0 + 1, "a"), ("tags", T0 + 2, "b")])
    assert reg.admit("r1", "r1", "scan", T0 + 3, T0, "c") == [("scan", T0 + 3, "c")]
    # without a token: the third message admits the robot, nothing was lost
    assert reg.admit("r2", "r2", "scan", T0 + 1, T0, "a") == []
    assert reg.admit("r2", "r2", "scan", T0 + 2, T0, "b") == []
    assert [m for _, _, m in reg.admit("r2", "r2", "scan", T0 + 3, T0, "c")] == ["a", "b", "c"]
    assert reg.totals()["joined"] == 2 and reg.totals()["on_probation"] == 0


def test_silent_robots_are_forgotten_and_start_afresh() -> None:
    reg = RobotRegistry(AdmissionPolicy(forget_after_ns=60 * S))
    admitted(reg, "r1")
    reg.admit("r1", "r1", "scan", T0 + 5 * S, T0 + 5 * S)
    for i in range(100):   # one message each, never admitted
        reg.admit(f"x{i}", f"x{i}", "scan", T0 + 6 * S, T0 + 6 * S)
    assert reg.forget_silent(T0 + 30 * S) == []
    reg.set_alive("r1", False, T0 + 7 * S)
    assert reg.forget_silent(T0 + 68 * S) == ["r1"]
    assert reg.robots == {} and reg.totals()["forgotten"] == 101
    # back after a reboot, with an older clock: served again, not refused as out of order
    reg.set_alive("r1", True, T0 + 70 * S)
    assert reg.admit("r1", "r1", "scan", T0 + 69 * S, T0 + 70 * S) == [("scan", T0 + 69 * S, None)]


def test_a_flood_of_new_ids_keeps_no_real_robot_out_and_logs_few_lines(
        caplog: pytest.LogCaptureFixture) -> None:
    reg = RobotRegistry(AdmissionPolicy(max_newcomers=500))
    with caplog.at_level(logging.INFO, logger="server.runtime.registry"):
        for i in range(2000):
            assert reg.admit(f"x{i}", f"x{i}", "scan", T0, T0) == []
            with pytest.raises(Refused):
                reg.admit(f"y{i}", f"x{i}", "scan", T0, T0)   # and a spoofed key each
            if i == 1000:   # a real robot without a token, amid the flood
                for k in range(3):
                    out = reg.admit("r2", "r2", "scan", T0 + k, T0)
                assert len(out) == 3
        admitted(reg, "r1")
        assert reg.admit("r1", "r1", "scan", T0 + 1, T0) == [("scan", T0 + 1, None)]
    assert reg.refused["key-mismatch"] == 2000 and reg.evicted == 1500
    assert len(reg.robots) == 502 and reg.totals()["on_probation"] == 500
    assert len(caplog.records) <= 20


# -- clocks that step --------------------------------------------------------------------------
def test_a_stamp_far_ahead_is_refused_alone_and_the_robot_goes_on() -> None:
    reg = admitted(RobotRegistry(), "r1")
    t = T0
    for k in range(20):
        t += S // 10
        stamp = t + 3600 * S if k == 5 else t
        try:
            out = reg.admit("r1", "r1", "scan", stamp, t)
            assert out == [("scan", stamp, None)]
        except Refused as e:
            assert k == 5 and e.reason == "clock-skew"
    c = reg.counters()["r1"]
    assert c["accepted_scan"] == 19 and c["refused_clock-skew"] == 1
    assert "clock_steps" not in c


def test_without_a_clock_of_its_own_the_stamps_say_when_a_robot_was_last_heard() -> None:
    """Replaying a recording (clock.source: stamps): a robot streaming for minutes is not
    taken for silent."""
    reg = RobotRegistry(AdmissionPolicy(forget_after_ns=60 * S))
    for k in range(200):
        reg.admit("r1", "r1", "scan", T0 + k * S, None)
    assert reg.forget_silent(T0 + 199 * S) == [] and reg.robots["r1"].admitted
    assert reg.forget_silent(T0 + 300 * S) == ["r1"]


def test_newcomers_without_a_token_join_at_a_bounded_rate_and_hold_little() -> None:
    """2,000 ids with three valid scans each: a burst joins, then two a second; those
    waiting keep only their latest messages. A robot with a token joins at once."""
    reg = RobotRegistry(AdmissionPolicy(probation=3, newcomers_per_s=2.0, newcomer_burst=10))
    joined = 0
    for k in range(3):
        for i in range(2000):
            now = T0 + k * S // 2 + i * 100_000       # 6,000 scans in about 1.2 s
            joined += bool(reg.admit(f"f{i}", f"f{i}", "scan", now, now))
    assert 10 <= joined <= 13
    waiting = [r for r in reg.robots.values() if not r.admitted]
    assert len(waiting) == 2000 - joined and max(len(r.held) for r in waiting) == 3
    assert reg.set_alive("r1", True, T0 + 2 * S)[0]
    assert reg.admit("r1", "r1", "scan", T0 + 2 * S, T0 + 2 * S) != []
    assert reg.trusted("r1") and not reg.trusted("f1999")
    # a newcomer that keeps sending joins when its turn comes
    later = T0 + 10 * S
    assert reg.admit("f1999", "f1999", "scan", later, later) != []
    assert reg.totals()["held_dropped"] == 0


def test_a_waiting_newcomer_keeps_only_its_latest_messages() -> None:
    reg = RobotRegistry(AdmissionPolicy(probation=3, newcomers_per_s=0.001, newcomer_burst=1))
    reg.admit("a", "a", "scan", T0, T0)
    reg.admit("a", "a", "scan", T0 + 1, T0 + 1)
    assert reg.admit("a", "a", "scan", T0 + 2, T0 + 2) != []       # the burst
    for k in range(10):
        assert reg.admit("b", "b", "scan", T0 + 10 + k, T0 + 10 + k) == []
    assert [t for _, t, _ in reg.robots["b"].held] == [T0 + 17, T0 + 18, T0 + 19]
    assert reg.totals()["held_dropped"] == 7
