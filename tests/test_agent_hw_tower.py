"""Camera tower: its line protocol, and the driver against a pty playing the stepper controller,
with synthetic depth images of a known room rendered from the camera's true pose."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial

from robot_agent.backend import Pose, Sweep
from robot_agent.drivers import tower_protocol as proto
from robot_agent.drivers.depth_scan import DepthView, fan
from robot_agent.drivers.fakes.tower import FakeTowerController
from robot_agent.drivers.tower import (
    DepthFrame,
    Tower,
    TowerHomingError,
    assemble,
    steps_per_rev,
)
from schemas.messages import ranges_from_mm
from schemas.se2 import transform_points
from tests.waiting import within

W, H = 320, 8
HFOV = math.radians(87.0)
FX = (W / 2) / math.tan(HFOV / 2)
CX = (W - 1) / 2
SPR = 6400
TRIGGER = 1234
BEAMS = 720
#: the room's walls in the world (= odometry) frame
X_MIN, X_MAX, Y_MIN, Y_MAX = -1.2, 2.2, -1.0, 1.6


def wall_hit(x: float, y: float, phi: np.ndarray) -> np.ndarray:
    """Distance from (x, y) inside the room to its wall along directions ``phi``."""
    c, s = np.cos(phi), np.sin(phi)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (X_MAX - x) / c, np.where(c < 0, (X_MIN - x) / c, np.inf))
        ty = np.where(s > 0, (Y_MAX - y) / s, np.where(s < 0, (Y_MIN - y) / s, np.inf))
    return np.minimum(tx, ty)


def still(pose: Pose) -> Callable[[int], Pose]:
    return lambda t_ns: pose


def driving(start: Pose, v: float, w: float) -> Callable[[int], Pose]:
    """The robot on an arc from ``start`` at the time of the first call."""
    t0: list[int] = []

    def at(t_ns: int) -> Pose:
        if not t0:
            t0.append(t_ns)
        t = (t_ns - t0[0]) * 1e-9
        x, y, th = start
        return (x + v / w * (math.sin(th + w * t) - math.sin(th)),
                y - v / w * (math.cos(th + w * t) - math.cos(th)), th + w * t)
    return at


def camera(fake: FakeTowerController, truth: Callable[[int], Pose]) -> Callable[[], DepthFrame]:
    """Depth frames (uint16 mm) of the room from the camera's true heading (the rotor's
    physical position) on the robot's true pose at the capture time."""
    def grab() -> DepthFrame:
        t = time.time_ns()
        x, y, th = truth(t)
        yaw = 2 * math.pi * (fake.physical - fake.trigger_step) / fake.steps_per_rev
        alpha = np.arctan2(CX - np.arange(W), FX)
        z = wall_hit(x, y, th + yaw + alpha) * np.cos(alpha)
        return DepthFrame(np.tile(np.rint(z * 1000), (H, 1)).astype(np.uint16), t)
    return grab


def wall_errors(sweep: Sweep, pose: Pose) -> np.ndarray:
    """Distance [m] of each return of ``sweep`` (seen from ``pose``) to the nearest wall."""
    r = ranges_from_mm(sweep.ranges_mm)
    theta = sweep.angle_min_rad + sweep.angle_increment_rad * np.arange(len(r))
    ok = np.isfinite(r)
    pts = transform_points(pose, np.stack([r[ok] * np.cos(theta[ok]),
                                           r[ok] * np.sin(theta[ok])], axis=1))
    return np.min(np.abs(np.stack([pts[:, 0] - X_MIN, pts[:, 0] - X_MAX,
                                   pts[:, 1] - Y_MIN, pts[:, 1] - Y_MAX])), axis=0)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Callable[..., tuple[FakeTowerController, Tower]]]:
    made: list[Any] = []

    def make(truth: Callable[[int], Pose] | None = None, open_: bool = True,
             settle_s: float = 0.02, **fake_kw: Any) -> tuple[FakeTowerController, Tower]:
        truth = truth or still((0.3, 0.1, 0.2))
        fake = FakeTowerController(tmp_path / "tower", steps_per_rev=SPR, trigger_step=TRIGGER,
                                   **fake_kw)
        made.append(fake)
        tower = Tower(str(fake.link), camera(fake, truth), truth, FX, CX, steps_per_rev=SPR,
                      settle_s=settle_s, beams=BEAMS, keepalive_s=0.05)
        made.append(tower)
        if open_:
            tower.open()
        return fake, tower
    yield make
    for thing in reversed(made):
        thing.close()


# -- the protocol on byte strings ---------------------------------------------------------------
def test_lines_carry_an_xor_checksum_and_replies_parse_strictly() -> None:
    # P ^ I ^ N ^ G = 0x50 ^ 0x49 ^ 0x4E ^ 0x47 = 0x10
    assert proto.encode("PING") == b"PING*10\n"
    assert proto.parse_command(b"PING*10\r") == ("PING", None)
    line = proto.encode("MOVE", -1600)
    assert proto.parse_command(line[:-1]) == ("MOVE", -1600)
    # the lines as the fake controller (and the firmware) write them
    for words, r in ((("PONG", 42, "READY"), proto.Reply("PONG", (42,), "READY")),
                     (("POS", -7, 100, "MOVING"), proto.Reply("POS", (-7, 100), "MOVING")),
                     (("ERR", "NOTRIGGER", 6410), proto.Reply("ERR", (6410,), "NOTRIGGER")),
                     (("ACK", "HOME"), proto.Reply("ACK", (), "HOME")),
                     (("HOMED", 1234), proto.Reply("HOMED", (1234,)))):
        assert proto.parse_reply(proto.encode(*words)[:-1]) == r
    bad = {b"PONG 42 READY": "no checksum",
           b"PONG 42 READY*11": "does not match",
           b"PONG 42 READY*1g": "hex",
           proto.encode("PONG", 42)[:-1]: "1 fields, expected 2",
           proto.encode("PONG", 42, "DANCING")[:-1]: "not one of",
           proto.encode("PONG", "4x2", "READY")[:-1]: "not an integer",
           proto.encode("HELLO", 1)[:-1]: "unknown reply",
           b"\xff\xfe*01": "printable",
           b"A" * 80: "at most"}
    for raw, why in bad.items():
        with pytest.raises(proto.TowerProtocolError, match=why):
            proto.parse_reply(raw)
    with pytest.raises(proto.TowerProtocolError, match="expected 1"):
        proto.parse_command(proto.encode("MOVE")[:-1])
    s = proto.LineSplitter()
    assert s.feed(b"AB\nC" + b"x" * 100) == [b"AB"] and s.feed(b"yy\nOK\n") == [b"OK"]
    assert s.overlong == 1
    assert steps_per_rev(200, 16, 2) == 6400


def test_a_view_origin_moves_its_points_and_the_default_changes_nothing() -> None:
    z = np.full((3, 5), 2.0)
    a0, r0 = fan(DepthView(0.3, z), fx=2.0, cx=2.0)
    a1, r1 = fan(DepthView(0.3, z, origin=(0.0, 0.0, 0.0)), fx=2.0, cx=2.0)
    assert np.array_equal(a0, a1) and np.array_equal(r0, r1)
    a2, r2 = fan(DepthView(0.3, z, origin=(0.5, -0.2, 0.1)), fx=2.0, cx=2.0)
    want = np.stack([0.5 + r0 * np.cos(a0 + 0.1), -0.2 + r0 * np.sin(a0 + 0.1)], axis=1)
    assert np.allclose(np.stack([r2 * np.cos(a2), r2 * np.sin(a2)], axis=1), want)


# -- the driver against the fake controller ------------------------------------------------------
@pytest.mark.parametrize(("start", "fired"), [(0, TRIGGER), (3000, SPR - 3000 + TRIGGER)])
def test_homing_finds_the_trigger(rig: Callable[..., tuple[FakeTowerController, Tower]],
                                  start: int, fired: int) -> None:
    fake, tower = rig(physical=start)
    assert tower.home_count == fired and tower.homed
    assert fake.count == 0 and fake.physical % SPR == TRIGGER and fake.lit()


def test_headings_are_reached_within_a_microstep(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    fake, tower = rig(physical=5000)
    for heading in (90, 270, 0, 180, 45):
        want = round(heading / 360 * SPR)
        assert tower.move_to(tower.heading_steps(heading)) == want
        off = (fake.physical - TRIGGER - want + SPR // 2) % SPR - SPR // 2   # modulo a turn
        assert abs(off) <= 1 and fake.state == "READY"


def test_a_sweep_of_four_frames_lies_on_the_walls(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    pose = (0.3, 0.1, 0.2)
    _, tower = rig(still(pose))
    t0 = time.monotonic()
    sweep = tower.sweep()
    took = time.monotonic() - t0
    assert [round(math.degrees(c.yaw_rad)) for c in tower.last_captures] == [0, 90, 180, 270]
    assert sweep.stamp_ns == tower.last_captures[-1].frame.stamp_ns
    err = wall_errors(sweep, pose)
    assert len(err) > 0.7 * BEAMS and err.max() < 0.03
    # the next sweep turns back: the cable never winds more than 270°
    tower.sweep()
    assert [round(math.degrees(c.yaw_rad)) for c in tower.last_captures] == [270, 180, 90, 0]
    assert took < 2.0


def test_motion_during_the_sweep_is_compensated(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    truth = driving((0.2, 0.0, 0.1), v=0.4, w=0.8)
    _, tower = rig(truth, settle_s=0.08)
    sweep = tower.sweep()
    caps = tower.last_captures
    assert caps[0].pose is not None and caps[-1].pose is not None
    turned = caps[-1].pose[2] - caps[0].pose[2]
    assert turned > 0.15                             # the robot really turned during the sweep
    ref = truth(sweep.stamp_ns)
    err = wall_errors(sweep, ref)
    assert len(err) > 0.6 * BEAMS and err.max() < 0.03
    raw = assemble(caps, FX, CX, beams=BEAMS, compensate=False)
    raw_err = wall_errors(raw, ref)
    # the early views turned and moved with the robot: a quarter of the returns is > 6 cm off
    assert raw_err.max() > 0.2 and np.percentile(raw_err, 75) > 0.06
    assert np.percentile(raw_err, 75) > 5 * np.percentile(err, 75)


def test_the_controller_stops_when_the_host_goes_silent(tmp_path: Path) -> None:
    fake = FakeTowerController(tmp_path / "tower", steps_per_rev=SPR, trigger_step=100,
                               step_rate=2000.0, timeout_s=0.3)
    port = serial.Serial(str(fake.link), 115200, timeout=0.05)
    try:
        port.write(proto.encode("HOME"))
        assert within(lambda: fake.state == "READY", 1.0)
        t_last = time.monotonic()   # before the write: the fake may read it before we go on
        port.write(proto.encode("MOVE", 6000))       # 3 s at 2000 microsteps/s
        assert within(lambda: fake.state == "MOVING", 0.2)
        assert within(lambda: fake.timeouts == 1, 1.0)
        assert fake.stopped_at is not None
        assert 0.3 <= fake.stopped_at - t_last <= 0.45
        count = fake.count
        assert 0 < count < 6000 and not fake.energised and fake.state == "UNHOMED"
        time.sleep(0.1)
        assert fake.count == count                  # held still
        lines = [proto.parse_reply(x) for x in port.read(4096).split(b"\n") if x]
        assert proto.Reply("TIMEOUT", (count,)) in lines
        port.write(proto.encode("MOVE", 100))     # no moving before homing again
        reply = proto.parse_reply(port.readline()[:-1])
        assert reply == proto.Reply("ERR", (0,), "NOTHOMED")
    finally:
        port.close()
        fake.close()


def test_the_drivers_keepalive_holds_the_controller_and_closing_releases_it(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    fake, tower = rig(timeout_s=0.3)
    time.sleep(0.8)
    assert fake.timeouts == 0 and fake.energised
    assert sum(cmd == "PING" for cmd, _ in fake.received) >= 8
    tower.close()
    assert within(lambda: fake.timeouts == 1, 1.0) and not fake.energised


def test_a_trigger_that_never_fires_is_a_typed_error(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    fake, tower = rig(open_=False)
    fake.trigger_broken = True
    with pytest.raises(TowerHomingError, match="trigger did not fire within 6409 microsteps"):
        tower.open()
    assert getattr(TowerHomingError, "user_error", False)
    assert tower.counters["homing_failures"] == 1 and not tower.homed
    assert fake.state == "UNHOMED" and fake.homes == 0
    assert tower._thread is not None and not tower._thread.is_alive()   # port released


def test_frames_without_odometry_are_counted_and_used_as_if_standing(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    pose = (0.3, 0.1, 0.2)
    _, tower = rig(still(pose))
    tower.odometry_at = lambda t_ns: None
    err = wall_errors(tower.sweep(), pose)
    assert tower.counters["no_odometry"] == 4
    assert len(err) > 0.7 * BEAMS and err.max() < 0.03


def test_garbage_replies_are_counted_and_do_not_crash(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    pose = (0.3, 0.1, 0.2)
    fake, tower = rig(still(pose))
    fake.inject(b"\x00\xff\xfe junk\n" + b"PONG 5 READY*00\n" + proto.encode("DONE", 1, 2)
                + proto.encode("HELLO") + b"A" * 200 + b"\n")
    assert within(lambda: tower.counters["bad_replies"] == 5, 1.0)
    fake.inject(b"\x07\x08")                        # spoils the next line
    sweep = tower.sweep()
    assert tower.counters["bad_replies"] == 6
    err = wall_errors(sweep, pose)
    assert len(err) > 0.7 * BEAMS and err.max() < 0.03
    assert tower._thread is not None and tower._thread.is_alive()


def test_a_position_error_makes_the_driver_home_again(
        rig: Callable[..., tuple[FakeTowerController, Tower]]) -> None:
    pose = (0.3, 0.1, 0.2)
    fake, tower = rig(still(pose))
    fake.lose_steps(40)                              # the rotor slipped at heading 0
    assert tower.move_to(tower.heading_steps(90)) == SPR // 4
    assert fake.position_errors == 1 and tower.counters["position_errors"] == 1
    assert tower.counters["rehomes"] == 1 and fake.homes == 2
    assert fake.physical - fake.count - TRIGGER in (0, SPR)   # back in step with the rotor
    err = wall_errors(tower.sweep(), pose)
    assert len(err) > 0.7 * BEAMS and err.max() < 0.03
