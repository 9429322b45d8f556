"""Robot clocks against the server's (``server.runtime.clock``): a late message is not a
stepped clock.

Each robot here streams at 10 Hz on a clock of its own; the tests give each message the time
the server received it, as a network that holds messages, jitters or delivers in bursts would,
and check what the server makes of the stamps.
"""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.runtime.clock import ClockPolicy, RobotClock, ServerClock, StampRefused

S = 1_000_000_000
MS = 1_000_000
T0 = 1_800_000_000 * S
PERIOD = 100 * MS
POLICY = ClockPolicy()


def stream(clock: RobotClock, sends: list[tuple[int, int, int]]
           ) -> tuple[list[tuple[int, int, int]], list[int]]:
    """Feed (true send time, robot stamp, receipt) in receipt order; returns the accepted
    (true time, mapped stamp, receipt) and the indices of the refused ones."""
    out, refused = [], []
    for k, (true_ns, stamp_ns, recv_ns) in enumerate(sorted(sends, key=lambda s: s[2])):
        try:
            out.append((true_ns, clock.map("scan", stamp_ns, recv_ns), recv_ns))
        except StampRefused:
            refused.append(k)
    return out, refused


def robot(seconds: float, offset_ns: int = 0, delay=lambda t: 2 * MS,
          step_at_s: float | None = None, step_ns: int = 0) -> list[tuple[int, int, int]]:
    """A robot's messages: (true send time, its stamp, receipt); its clock reads
    ``offset_ns`` off, and steps by ``step_ns`` at ``step_at_s``. Its link delivers in order,
    as a TCP connection does."""
    out: list[tuple[int, int, int]] = []
    for k in range(round(seconds * 10)):
        t = T0 + k * PERIOD
        stamp = t + offset_ns + (step_ns if step_at_s is not None and t >= T0 + step_at_s * S
                                 else 0)
        out.append((t, stamp, max(t + delay(t), out[-1][2] if out else 0)))
    return out


@pytest.mark.parametrize("burst_s", [0.5, 2.0, 5.0, 15.0])
def test_a_delay_burst_neither_rebases_nor_refuses(burst_s: float) -> None:
    """A link that holds every message for ``burst_s`` (a Wi-Fi roam) and then delivers them
    at once: the offset stays, nothing is refused, every mapped stamp is the true one."""
    start, end = T0 + 10 * S, T0 + 10 * S + round(burst_s * S)

    def delay(t: int) -> int:
        return (end - t) + 3 * MS if start <= t < end else 2 * MS

    clock = RobotClock(POLICY)
    out, refused = stream(clock, robot(40.0, delay=delay))
    assert refused == [] and clock.steps == 0 and clock.adjustments == 0
    assert clock.offset_ns == 0
    assert max(abs(mapped - true) for true, mapped, _ in out) == 0


def test_jitter_and_a_slow_link_keep_the_offset_within_tolerance() -> None:
    rng = random.Random(3)
    clock = RobotClock(POLICY)
    out, refused = stream(clock, robot(120.0, delay=lambda t: 10 * MS + rng.randrange(300 * MS)))
    assert refused == [] and clock.steps == 0
    assert max(abs(mapped - true) for true, mapped, _ in out) <= POLICY.tolerance_ns


def test_a_link_that_is_always_slow_is_followed_as_an_adjustment() -> None:
    """Passive synchronisation cannot tell a clock 150 ms behind from a link 150 ms slow: the
    offset follows the smallest (receipt - stamp), as an adjustment, not a step."""
    rng = random.Random(4)
    clock = RobotClock(POLICY)
    _, refused = stream(clock, robot(60.0, delay=lambda t: 150 * MS + rng.randrange(20 * MS)))
    assert refused == [] and clock.steps == 0 and clock.adjustments == 1
    assert 150 * MS <= clock.offset_ns <= 155 * MS


@pytest.mark.parametrize("step_s", [-3600.0, -1.0, 1.0, 3600.0, 86_400.0 * 365 * 50])
def test_a_clock_that_steps_is_rebased_within_a_second(step_s: float) -> None:
    clock = RobotClock(POLICY)
    out, refused = stream(clock, robot(30.0, step_at_s=10.0, step_ns=round(step_s * S)))
    assert clock.steps == 1
    # within a second of the step the stamps are right again, and stay right
    assert all(abs(mapped - true) <= 5 * MS for true, mapped, _ in out if true >= T0 + 11 * S)
    assert all(abs(mapped - true) <= 5 * MS for true, mapped, _ in out if true < T0 + 10 * S)
    assert all(100 <= k <= 103 for k in refused), refused   # at most the confirming few
    mapped = [m for _, m, _ in out]
    assert mapped == sorted(mapped) and len(set(mapped)) == len(mapped)


def test_a_small_step_back_costs_at_most_a_scan_and_is_not_counted_as_a_step() -> None:
    clock = RobotClock(POLICY)
    out, refused = stream(clock, robot(30.0, step_at_s=10.0, step_ns=-100 * MS))
    assert len(refused) <= 1 and clock.steps == 0
    # the window's minimum catches up once the messages from before the step have left it
    assert all(abs(mapped - true) <= POLICY.tolerance_ns for true, mapped, _ in out
               if true >= T0 + 10 * S + POLICY.window_ns + S)


def test_a_clock_that_stepped_back_while_the_robot_was_silent_is_rebased_by_the_window(
        ) -> None:
    """Stamps do not go backwards (the gap is longer than the step), but every message from
    then on is late by the step: once the messages from before it have left the window, the
    offset follows."""
    sends = [s for s in robot(40.0, step_at_s=10.0, step_ns=-2 * S)
             if not T0 + 10 * S <= s[0] < T0 + 14 * S]       # 4 s silent, clock back 2 s
    clock = RobotClock(POLICY)
    out, refused = stream(clock, sends)
    assert refused == [] and clock.steps == 1
    right_again = min(true for true, mapped, _ in out
                      if true > T0 + 14 * S and abs(mapped - true) <= 5 * MS)
    assert right_again <= T0 + 10 * S + POLICY.window_ns + S


def test_a_clock_far_off_at_first_contact_is_taken_as_it_is() -> None:
    clock = RobotClock(POLICY)
    out, refused = stream(clock, robot(5.0, offset_ns=-50 * 365 * 86_400 * S))
    assert refused == [] and clock.steps == 0
    assert max(abs(mapped - true) for true, mapped, _ in out) <= 5 * MS


def test_a_lone_stamp_ahead_is_taken_at_its_receipt_and_moves_nothing() -> None:
    clock = RobotClock(POLICY)
    sends = robot(10.0)
    t, stamp, recv = sends[50]
    sends[50] = (t, stamp + 700 * MS, recv)          # a glitch within max_skew: kept
    t, stamp, recv = sends[60]
    sends[60] = (t, stamp + 3600 * S, recv)          # far ahead: refused
    out, refused = stream(clock, sends)
    assert refused == [60] and clock.steps == 0 and clock.offset_ns == 0
    assert [m for tr, m, r in out if tr == sends[50][0]] == [sends[50][2]]


def test_a_lockstep_receipt_known_only_to_its_step_is_not_evidence() -> None:
    """In lockstep the server knows a receipt only to the step: a scan may arrive before the
    step's clock message is handed over. Stamps one step ahead never re-base."""
    clock = RobotClock(POLICY)
    for k in range(300):
        stamp = T0 + k * PERIOD
        seen = stamp - (PERIOD if k % 7 == 3 else 0)
        assert clock.map("scan", stamp, seen, PERIOD) == stamp
    assert clock.steps == clock.adjustments == 0


def test_the_simulated_receipt_follows_the_clock_messages_by_their_own_receipt() -> None:
    sc = ServerClock("sim")
    wall0 = 5 * S
    # real time x2: step k's clock message reached us at wall0 + k * 50 ms; handed over late
    # and out of order (the server was busy)
    for k in (0, 1, 3, 2):
        sc.on_sim_clock(k * PERIOD, wall0 + k * 50 * MS, PERIOD, 2.0)
    assert sc.receive_ns(wall0 + 2 * 50 * MS + 5 * MS) == (2 * PERIOD + 10 * MS, 0)
    # after the newest clock message known: the next one may be on its way to us
    assert sc.receive_ns(wall0 + 3 * 50 * MS + 1 * MS) == (3 * PERIOD + 2 * MS, PERIOD)
    lock = ServerClock("sim")
    lock.on_sim_clock(7 * PERIOD, wall0, PERIOD, 0.0)
    assert lock.receive_ns(wall0 + 3 * S) == (7 * PERIOD, PERIOD)
    assert ServerClock("wall").receive_ns(wall0) == (wall0, 0)
    assert ServerClock("stamps").receive_ns(wall0) == (None, 0)


def test_a_rebase_takes_the_receipts_as_the_server_knows_them_by_then() -> None:
    """A simulation's clock message may be handed over after the scan it preceded, so that
    scan's receipt is first placed from the step before. Where the simulation was catching up
    (steps faster than real time) that is too early; the re-base the scan helps confirm takes
    its receipt as known by then."""
    sc = ServerClock("sim")
    clock = RobotClock(POLICY)
    for k in range(60):
        stamp = k * PERIOD + (S if k >= 30 else 0)       # the robot's clock jumps 1 s ahead
        at = 10 * S + (k * PERIOD if k < 30 else 3 * S + (k - 30) * 20 * MS)   # catching up
        late = k == 31                                   # its clock message comes after it
        if not late:
            sc.on_sim_clock(k * PERIOD, at, PERIOD, 1.0)
        recv, slack = sc.receive_ns(at + 3 * MS)
        assert recv is not None
        clock.map("scan", stamp, recv, slack, lambda w=at + 3 * MS: sc.receive_ns(w)[0])
        if late:
            sc.on_sim_clock(k * PERIOD, at, PERIOD, 1.0)
    assert clock.steps == 1 and clock.offset_ns == -S + 3 * MS


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(-10**12, 10**12), st.integers(0, 10**9)), max_size=80))
def test_mapped_stamps_go_forward_and_never_run_ahead_of_their_receipt(
        jumps: list[tuple[int, int]]) -> None:
    clock = RobotClock(POLICY)
    server = robot_ns = T0
    last = None
    for n, (dstamp, dserver) in enumerate(jumps):
        server += dserver
        robot_ns = max(0, robot_ns + dstamp)
        try:
            t = clock.map("scan", robot_ns, server)
        except StampRefused:
            continue
        assert last is None or t > last
        assert t <= server + POLICY.tolerance_ns + n
        last = t
