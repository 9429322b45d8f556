"""The motor-base firmware, compiled for the ATmega2560, running in simavr with two simulated
motors (deploy/firmware/hil/hil_base.c), driven by the agent's real driver over a pty.

Every time checked here is simulated time, read from the harness's log of the board's wire and
pins; the harness keeps simulated time from running ahead of wall time, so the driver's own
wall-clock timers (50 ms keep-alive, 0.4 s hold, 0.5 s link timeout) meet a board of real speed.
"""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from robot_agent.drivers import base_protocol as proto
from robot_agent.drivers.base import SerialBase
from tests.support_firmware import FIRMWARE, Board, Report, build
from tests.waiting import within

#: starts the simulator process: the e2e tier
#: real time against wall clocks: run alone, after the others (``make test``)
pytestmark = [pytest.mark.e2e, pytest.mark.realtime]

TRACK, RADIUS, TICKS = 0.3, 0.05, 1000.0
M_PER_TICK = 2 * math.pi * RADIUS / TICKS
PERIOD_US = 20_000


@pytest.fixture(scope="module")
def built() -> None:
    build()


def start(link: Path, *options: str) -> tuple[Board, SerialBase]:
    board = Board(link, *options)
    base = SerialBase(str(link), TRACK, RADIUS, TICKS, reconnect_s=0.2)
    base.start()
    assert base.connected.wait(10.0), board.diagnostics()
    return board, base


@pytest.fixture
def rig(built: None, tmp_path: Path) -> Iterator[tuple[Board, SerialBase]]:
    board, base = start(tmp_path / "base")
    yield board, base
    base.close()
    board.close()


def speeds_sent(board: Board, after_us: int = 0) -> list[tuple[int, tuple[int, int]]]:
    """(time, (left, right) ticks/s) of the valid SPEED frames the board received."""
    return [(t, proto.parse_speed(f)[:2]) for t, f in board.received()
            if t >= after_us and f is not None and f.kind == proto.SPEED]


def within_pct(value: float, target: float, pct: float) -> bool:
    return abs(value - target) <= abs(target) * pct / 100


def test_speed_commands_are_followed_by_closed_loop_control(
        rig: tuple[Board, SerialBase]) -> None:
    board, base = rig
    figures = []
    for v, w in [(0.2, 0.0), (0.0, 1.0), (-0.15, -0.5)]:
        t_start = board.now_us()
        board.run_for(1.5, lambda v=v, w=w: base.set_velocity(v, w))
        t_end = board.now_us()
        vl, vr = proto.wheel_speeds(v, w, TRACK)
        want = (round(vl / M_PER_TICK), round(vr / M_PER_TICK))
        sent = [s for s in speeds_sent(board, t_start) if s[0] < t_end]
        first = next(i for i, s in enumerate(sent) if s[1] == want)   # after those in flight
        assert len(sent) - first > 10 and all(s[1] == want for s in sent[first:])
        t_cmd = sent[first][0]
        samples = board.samples_between(t_cmd, t_end)
        # settled: from some time on, every sample within 10 % on both wheels
        ok = [all(within_pct(s.speed[i], want[i], 10) for i in (0, 1)) for s in samples]
        first_bad_from_end = next((k for k, good in enumerate(reversed(ok)) if not good),
                                  len(ok))
        settled = samples[len(ok) - first_bad_from_end] if first_bad_from_end else None
        assert settled is not None, f"never settled on {want}: {samples[-1]}"
        settle_s = (settled.t_us - t_cmd) / 1e6
        assert settle_s < 0.6 and t_end - settled.t_us > 500_000
        # overshoot: how far past the new target, as a share of the step to it
        s0 = samples[0].speed
        overshoot = max(max((s.speed[i] - want[i]) / (want[i] - s0[i]) for s in samples)
                        for i in (0, 1))
        last = board.samples_between(t_end - 500_000, t_end)
        error = max(abs(sum(s.speed[i] for s in last) / len(last) / want[i] - 1) for i in (0, 1))
        figures.append(f"{want}: settled within 10 % in {settle_s * 1000:.0f} ms, "
                       f"overshoot {overshoot * 100:.0f} %, mean error of the last 0.5 s "
                       f"{error * 100:.1f} %")
    base.set_velocity(0.0, 0.0)
    board.run_for(1.0)              # the wheels coast to rest
    last = board.reports()[-1].enc
    # every encoder edge counted, with the right sign on the mirror-mounted side
    assert (last.left_ticks, last.right_ticks) == board.samples[-1].ticks
    odo = base.odometry_at(time.time_ns() - 100_000_000)
    assert odo is not None
    dl, dr = (t * M_PER_TICK for t in board.samples[-1].ticks)
    assert odo.pose[2] == pytest.approx((dr - dl) / TRACK, abs=0.01)
    print("speed control (simulated time):", "; ".join(figures))


def test_reports_come_every_20_ms_of_simulated_time(rig: tuple[Board, SerialBase]) -> None:
    board, base = rig
    board.run_for(2.0, lambda: base.set_velocity(0.25, 0.4))   # both directions busy
    reports = board.reports()
    assert len(reports) >= 95
    gaps = [b.t_us - a.t_us for a, b in itertools.pairwise(reports)]
    assert all(abs(g - PERIOD_US) <= 2_000 for g in gaps), gaps
    stamps = [r.enc.time_ms for r in reports]
    assert all(b - a == 20 for a, b in itertools.pairwise(stamps))
    print(f"report period (simulated): {len(gaps)} gaps, min {min(gaps) / 1000:.3f} ms, "
          f"max {max(gaps) / 1000:.3f} ms, mean {sum(gaps) / len(gaps) / 1000:.3f} ms")


def test_silence_stops_the_motors_within_the_frames_timeout(
        rig: tuple[Board, SerialBase]) -> None:
    board, base = rig
    renew = lambda: base.set_velocity(0.2, 0.0)     # noqa: E731
    board.run_for(1.0, renew)
    board.command("mute")                           # the host's line goes quiet
    assert board.wait(lambda: any(i.startswith("muted") for i in board.info))
    board.run_for(0.6, renew)                       # the agent goes on commanding, unheard
    # the last SPEED that reached the board: bytes the harness had already taken from the
    # line when it went quiet still arrive after the "muted" line (a busy host writes
    # frames in bursts), so the anchor is the last frame received, not the last before it
    last_t, last = max((t, f) for t, f in board.received()
                       if f is not None and f.kind == proto.SPEED)
    assert last_t < board.info_time("muted") + 50_000
    timeout_ms = proto.parse_speed(last)[2]
    assert timeout_ms == base.firmware_timeout_ms
    stops = [board.stopped_at(side, last_t + 1) for side in "LR"]
    assert None not in stops
    delays = [(s - last_t) / 1000 for s in stops]
    # the board counts whole milliseconds: it stops in (timeout - 1, timeout] after the
    # frame reached it (its last byte plus the UART's byte time, 0.1 ms after t_last)
    assert all(timeout_ms - 1 < d <= timeout_ms + 0.5 for d in delays), delays
    # the next report says why
    after = [r for r in board.reports() if r.t_us > max(stops)]
    assert after[0].enc.flags & proto.FLAG_TIMEOUT
    assert not after[1].enc.flags & proto.FLAG_DRIVING
    # the line back: the agent's renewed commands drive again
    board.command("unmute")
    board.run_for(0.5, renew)
    assert board.samples[-1].speed[0] > 400
    print(f"silence: motors stopped {delays[0]:.2f} / {delays[1]:.2f} ms after the last SPEED "
          f"(timeout {timeout_ms} ms)")


def test_a_corrupted_frame_stops_the_motors_and_is_flagged(
        rig: tuple[Board, SerialBase]) -> None:
    board, base = rig
    renew = lambda: base.set_velocity(0.2, 0.0)     # noqa: E731
    board.run_for(1.0, renew)
    assert board.samples[-1].speed[0] > 500
    # host -> board: a bit flipped on the wire in a SPEED frame
    board.command("corrupt-rx")
    assert board.wait(lambda: any(i.startswith("corrupted RX") for i in board.info), 10)
    board.run_for(0.2, renew)
    bad = [t for t, f in board.received() if f is None]
    assert len(bad) == 1
    stops = [board.stopped_at(side, bad[0]) for side in "LR"]
    assert None not in stops and max(stops) - bad[0] <= 1_000
    flagged = [r for r in board.reports() if r.enc.flags & proto.FLAG_BAD_FRAME]
    assert len(flagged) == 1 and 0 < flagged[0].t_us - bad[0] <= PERIOD_US + 2_000
    assert within(lambda: base.counters["firmware_bad_frames"] == 1, 2.0)
    # the next SPEED (the driver renews every 50 ms) drives again
    board.run_for(0.5, renew)
    assert board.samples[-1].speed[0] > 500
    print(f"bad frame from the host: motors stopped {(max(stops) - bad[0]) / 1000:.3f} ms "
          f"after it, flagged in the report {(flagged[0].t_us - bad[0]) / 1000:.1f} ms later")

    # board -> host: the driver rejects the report and stops the motors itself, although the
    # agent goes on commanding (so no STOP comes from its hold running out)
    board.command("corrupt-tx")
    assert board.wait(lambda: any(i.startswith("corrupted TX") for i in board.info), 10)
    t_bad = board.info_time("corrupted TX")
    board.run_for(0.3, renew)
    assert base.counters["bad_frames"] == 1 and base.counters["hold_expired"] == 0
    stop_frames = [t for t, f in board.received()
                   if t > t_bad and f is not None and f.kind == proto.STOP]
    assert stop_frames
    stops = [board.stopped_at(side, stop_frames[0]) for side in "LR"]
    assert None not in stops and max(stops) - stop_frames[0] <= 1_000
    print(f"bad frame from the board: the driver's STOP reached it "
          f"{(stop_frames[0] - t_bad) / 1000:.1f} ms later")


def test_board_time_and_tick_counters_wrap(built: None, tmp_path: Path) -> None:
    start_ms = 2**32 - 1_200                        # 1.2 s before the board's clock wraps
    start_ticks = 2**31 - 900                       # int32 counters 900 ticks from wrapping
    board, base = start(tmp_path / "base", "--set", f"boardMs={start_ms}",
                        "--set", f"leftTicks={start_ticks}", "--set", f"rightTicks={start_ticks}")
    try:
        t0 = board.now_us()
        board.run_for(2.5, lambda: base.set_velocity(0.2, 0.0))
        base.set_velocity(0.0, 0.0)
        board.run_for(0.8)
        reports = board.reports()
        stamps = [r.enc.time_ms for r in reports]
        assert stamps[0] >= start_ms and stamps[-1] < 5_000          # it wrapped
        assert all((b - a) % 2**32 == 20 for a, b in itertools.pairwise(stamps))
        gaps = [b.t_us - a.t_us for a, b in itertools.pairwise(reports)]
        assert all(abs(g - PERIOD_US) <= 2_000 for g in gaps)
        lefts = [r.enc.left_ticks for r in reports]
        assert lefts[0] > 0 and lefts[-1] < 0                        # wrapped to negative
        steps = [proto.tick_delta(b, a) for a, b in itertools.pairwise(lefts)]
        assert all(0 <= s <= 20 for s in steps)                     # ≤ 1000 ticks/s, no jump
        # every edge counted across the wrap, on both wheels: the last report's counts are the
        # true ones of the moment it latched them, in the period before it left the board (a
        # wheel can still creep by an edge after the last report, so not the last sample's)
        last = reports[-1]
        around = board.samples_between(last.t_us - PERIOD_US - 5_000, last.t_us + 5_000)
        assert around
        for i, got in enumerate((last.enc.left_ticks, last.enc.right_ticks)):
            truths = [s.ticks[i] for s in around]
            assert min(truths) <= (got - start_ticks) % 2**32 <= max(truths), (i, got, truths)
        true = board.samples[-1].ticks
        # the speed loop did not notice: within 10 % of the command around both wraps
        want = round(0.2 / M_PER_TICK)
        wraps = [next(b.t_us for a, b in itertools.pairwise(reports)
                      if key(a) > key(b)) for key in (lambda r: r.enc.time_ms,
                                                      lambda r: r.enc.left_ticks,
                                                      lambda r: r.enc.right_ticks)]
        for wrap in wraps:
            assert wrap - t0 > 700_000
            near = board.samples_between(wrap - 200_000, wrap + 200_000)
            assert near and all(within_pct(s.speed[i], want, 10) for s in near for i in (0, 1))
        # the driver's odometry runs on through both wraps
        odo = base.odometry_at(time.time_ns() - 100_000_000)
        assert odo is not None and base.connected.is_set() and base.counters["connects"] == 1
        assert odo.pose[0] == pytest.approx(sum(true) / 2 * M_PER_TICK, abs=0.005)
        print(f"wraps: board time {stamps[0]} -> {stamps[-1]} ms, left ticks {lefts[0]} -> "
              f"{lefts[-1]}, odometry x {odo.pose[0]:.3f} m for {sum(true) / 2:.0f} true ticks")
    finally:
        base.close()
        board.close()


def test_the_driver_reconnects_after_the_port_closes(rig: tuple[Board, SerialBase]) -> None:
    board, base = rig
    renew = lambda: base.set_velocity(0.2, 0.0)     # noqa: E731
    board.run_for(1.0, renew)
    before = base.odometry_at(time.time_ns() - 50_000_000)
    board.command("unplug")                         # the USB cable out: the board loses power
    assert within(lambda: not base.connected.is_set(), 5.0)
    assert base.counters["base_BaseDisconnected"] + base.counters["base_BaseTimeout"] >= 1
    board.command("plug reset")                     # ... and in again: the board restarts
    assert base.connected.wait(10.0) and base.counters["connects"] == 2
    t_reset = board.info_time("reset")
    first = next(f for t, f in board.received() if t > t_reset)
    assert first is not None and first.kind == proto.STOP
    assert all(board.stopped_at(side, t_reset) == t_reset for side in "LR")
    # odometry goes on from where it was, although the board's counters restarted at 0
    after = base.odometry_at(time.time_ns() - 50_000_000)
    assert before is not None and after is not None and before.pose[0] > 0.1
    assert after.pose[0] == pytest.approx(before.pose[0], abs=0.05)
    reports: list[Report] = [r for r in board.reports() if r.t_us > t_reset]
    assert reports and reports[0].enc.time_ms < 1_000
    # and the base drives again
    board.run_for(1.0, renew)
    assert within_pct(board.samples[-1].speed[0], round(0.2 / M_PER_TICK), 10)


def test_calibration_measures_the_simulated_motors(built: None, tmp_path: Path) -> None:
    board = Board(tmp_path / "base", "--max-speed", "2100,1800", "--tau", "0.1")
    try:
        out = subprocess.run([sys.executable, str(FIRMWARE / "calibrate.py"), "--port",
                              str(board.link)], capture_output=True, text=True, timeout=120)
    finally:
        board.close()
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    found = [(float(line.split()[3]), float(line.split()[7])) for line in lines[:2]]
    (left, tau_l), (right, tau_r) = found
    assert left == pytest.approx(2100, rel=0.03) and right == pytest.approx(1800, rel=0.03)
    assert 0.07 <= tau_l <= 0.14 and 0.07 <= tau_r <= 0.14
    assert lines[2].startswith("const float KFF = 1.0f / ") and "TAU_S" in lines[2]
    print("calibration on the simulated motors:", "; ".join(lines[:2]))
