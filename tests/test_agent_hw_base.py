"""Motor base: kinematics, frames, and the driver against a pty playing the microcontroller."""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from robot_agent.drivers import base_protocol as proto
from robot_agent.drivers.base import SerialBase
from robot_agent.drivers.fakes.base import FakeMicrocontroller
from tests.waiting import within

TRACK, RADIUS, TICKS = 0.3, 0.05, 1000.0
M_PER_TICK = 2 * math.pi * RADIUS / TICKS


def test_wheel_speeds_follow_the_differential_drive_formula() -> None:
    assert proto.wheel_speeds(0.4, 0.0, TRACK) == (0.4, 0.4)            # ω = 0: straight
    assert proto.wheel_speeds(0.0, 2.0, TRACK) == pytest.approx((-0.3, 0.3))  # on the spot
    rng = np.random.default_rng(0)
    for v, w, b in rng.uniform([-1, -3, 0.1], [1, 3, 0.8], (50, 3)):
        vl, vr = proto.wheel_speeds(v, w, b)
        assert vl == pytest.approx(v - w * b / 2) and vr == pytest.approx(v + w * b / 2)
        assert (vl + vr) / 2 == pytest.approx(v) and (vr - vl) / b == pytest.approx(w)


def test_odometry_integration_follows_arcs() -> None:
    # constant v, ω for 2 s in 200 steps ends on the circle of radius v/ω
    v, w, b, dt = 0.3, 0.5, TRACK, 0.01
    vl, vr = proto.wheel_speeds(v, w, b)
    pose = (0.0, 0.0, 0.0)
    for _ in range(200):
        pose = proto.integrate(pose, vl * dt, vr * dt, b)
    th = w * 2.0
    assert pose == pytest.approx((v / w * math.sin(th), v / w * (1 - math.cos(th)), th),
                                 abs=1e-9)
    assert proto.integrate((1.0, 2.0, math.pi / 2), 0.1, 0.1, b) == pytest.approx(
        (1.0, 2.1, math.pi / 2))
    assert proto.tick_delta(-2**31 + 5, 2**31 - 5) == 10                  # wrap-around


def test_frames_round_trip_and_bad_bytes_are_skipped() -> None:
    enc = proto.Encoders(123456, -42, 2**31 - 1, proto.FLAG_DRIVING)
    raw = enc.encode(7)
    assert raw[:2] == b"\xaa\x55" and raw[2] == proto.ENCODERS and raw[4] == 13
    assert proto.crc8(b"123456789") == 0xF4     # the CRC-8 check value of its catalogue
    speed = proto.speed_frame(8, 1000, -1000, 300)
    flipped = bytearray(raw)
    flipped[9] ^= 0x10
    p = proto.FrameParser()
    frames = p.feed(b"\x00\xaa\x13" + bytes(flipped) + raw[:5]) + p.feed(raw[5:] + speed)
    assert [proto.parse_encoders(f) for f in frames[:1]] == [enc]
    assert proto.parse_speed(frames[1]) == (1000, -1000, 300)
    assert p.bad_frames == 1 and len(frames) == 2
    with pytest.raises(proto.BaseProtocolError, match="not an ENCODERS frame"):
        proto.parse_encoders(frames[1])


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[FakeMicrocontroller, SerialBase]]:
    mcu = FakeMicrocontroller(tmp_path / "base")
    base = SerialBase(str(mcu.link), TRACK, RADIUS, TICKS, reconnect_s=0.2)
    base.start()
    assert base.connected.wait(3.0)
    yield mcu, base
    base.close()
    mcu.close()


def drive(base: SerialBase, v: float, w: float, seconds: float) -> None:
    """Renew the command at 10 Hz, as the server's controller does."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        base.set_velocity(v, w)
        time.sleep(0.1)


def test_commands_become_wheel_ticks_and_ticks_become_odometry(
        rig: tuple[FakeMicrocontroller, SerialBase]) -> None:
    mcu, base = rig
    t0 = time.time_ns()
    drive(base, 0.2, 0.0, 1.0)
    want = round(0.2 / M_PER_TICK)
    assert mcu.motor_log[1][1] == (want, want)
    drive(base, 0.0, 1.0, 0.8)
    vl, vr = proto.wheel_speeds(0.0, 1.0, TRACK)
    assert mcu.speed == (round(vl / M_PER_TICK), round(vr / M_PER_TICK))
    base.set_velocity(0.0, 0.0)
    assert within(lambda: mcu.speed == (0, 0), 0.1)
    time.sleep(0.2)
    end = base.odometry_at(time.time_ns() - 50_000_000)
    assert end is not None
    # odometry from the ticks the wheels really turned
    dl, dr = (t * M_PER_TICK for t in mcu.ticks)
    x, y, th = end.pose
    assert th == pytest.approx((dr - dl) / TRACK, abs=0.02)
    assert math.hypot(x, y) == pytest.approx(0.2, abs=0.03) and abs(y) < 0.02
    # interpolated poses between frames lie between their neighbours and are monotone in x
    xs = [o.pose[0] for o in (base.odometry_at(t0 + k * 10_000_000) for k in range(5, 100))
          if o is not None]
    assert len(xs) > 50 and all(b >= a - 1e-9 for a, b in itertools.pairwise(xs))
    assert base.odometry_at(t0 - 10**9) is None                     # before the history
    assert base.odometry_at(time.time_ns() + 10**9) is None         # too far ahead


def test_motors_stop_within_half_a_second_when_commands_stop(
        rig: tuple[FakeMicrocontroller, SerialBase]) -> None:
    mcu, base = rig
    base.set_velocity(0.3, 0.5)
    t_last = time.monotonic()
    assert within(lambda: mcu.speed != (0, 0), 0.5)
    assert within(lambda: mcu.stopped_since() is not None, 1.0)
    assert mcu.stopped_since() - t_last <= 0.5       # type: ignore[operator]
    assert base.counters["hold_expired"] == 1


def test_a_bad_frame_stops_the_motors_and_unplugging_reconnects(
        rig: tuple[FakeMicrocontroller, SerialBase]) -> None:
    mcu, base = rig
    drive(base, 0.2, 0.0, 0.3)
    assert mcu.speed != (0, 0)
    mcu.corrupt_next = True
    t0 = time.monotonic()
    assert within(lambda: mcu.speed == (0, 0), 0.5)
    assert base.counters["bad_frames"] == 1 and time.monotonic() - t0 < 0.5

    drive(base, 0.2, 0.0, 0.5)
    before = base.odometry_at(time.time_ns() - 30_000_000)
    mcu.unplug()
    assert within(lambda: not base.connected.is_set(), 2.0)
    assert base.counters["base_BaseDisconnected"] + base.counters["base_BaseTimeout"] >= 1
    base.set_velocity(0.2, 0.0)          # commands while unplugged are dropped, not queued
    n_received = len(mcu.received)
    mcu.plug(restart=True)
    assert base.connected.wait(3.0) and base.counters["connects"] == 2
    first = mcu.received[n_received]
    assert first.kind == proto.STOP and mcu.speed == (0, 0)
    time.sleep(0.2)
    after = base.odometry_at(time.time_ns() - 30_000_000)
    assert before is not None and after is not None
    # the board restarted its counters: the pose continues instead of jumping back to 0
    assert after.pose[0] == pytest.approx(before.pose[0], abs=0.05) and after.pose[0] > 0.05


def test_the_boards_flags_count_in_every_report() -> None:
    """A bad-frame flag counts even in the first report after connecting or in one whose
    time does not advance; a stop on silence counts once per stop."""
    base = SerialBase("/dev/null-never-opened", TRACK, RADIUS, TICKS)
    t = time.time_ns()
    base._on_encoders(proto.Encoders(1000, 0, 0, proto.FLAG_BAD_FRAME), t)   # first report
    base._on_encoders(proto.Encoders(1000, 0, 0, proto.FLAG_BAD_FRAME), t)   # same time
    assert base.counters["firmware_bad_frames"] == 2
    for ms, flags in ((1020, proto.FLAG_TIMEOUT), (1040, proto.FLAG_TIMEOUT), (1060, 0),
                      (1080, proto.FLAG_TIMEOUT)):
        base._on_encoders(proto.Encoders(ms, 0, 0, flags), t + (ms - 1000) * 1_000_000)
    assert base.counters["firmware_timeouts"] == 2
