"""A depth camera on a turning tower: four headings make one 360° pseudo-scan.

The tower's stepper controller speaks ``tower_protocol`` over a serial port. The driver homes
it when it opens (the reference trigger's edge becomes position 0; ``zero_offset_steps`` more
is the camera looking along the robot's x axis), then each ``sweep()`` turns the camera to the
configured headings (default 0°, 90°, 180°, 270°; every other sweep in reverse order, so the
cable never winds more than the span of the headings), waits at each for the move to finish and
``settle_s`` more, takes a depth frame from ``frame_source`` and the robot's odometry pose at the
frame's capture time from ``odometry_at``.

A sweep lasts a second or so, and the robot may move meanwhile. The views are merged in the
robot frame of one reference instant, the capture time of the sweep's last frame, which is the
sweep's stamp: each view carries the robot's pose at its capture relative to the pose at the
reference instant (``between(pose_ref, pose_capture)``, from odometry), and ``depth_scan``
moves its beams by it. A frame without an odometry pose is used as if the robot stood still
(and counted as ``no_odometry``).

Stopping and errors:

- a background thread reads the controller's replies and sends PING whenever nothing else was
  sent for ``keepalive_s``; if this process dies or hangs, the controller stops and
  de-energises the coils after its own silence timeout (and reports TIMEOUT);
- replies that fail parsing (framing, checksum, fields) are counted as ``bad_replies`` and
  logged, never raised from the thread; the waits do not depend on any one reply, as the
  PONGs of the keep-alive carry the position and state too;
- ERR POSITION (the controller found lost steps), ERR NOTHOMED or a controller that fell back
  to UNHOMED (silence timeout) make the driver home again and repeat the move, once;
- a trigger that never fires is ``TowerHomingError``; no valid reply for ``link_timeout_s``
  is ``TowerTimeout``; a serial failure is ``TowerDisconnected``.

The driver's methods are for one caller thread at a time (the agent's sweep loop).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import serial

from robot_agent.backend import Pose, Sweep
from robot_agent.drivers import tower_protocol as proto
from robot_agent.drivers.depth_scan import DepthView, pseudo_scan
from schemas.se2 import between

log = logging.getLogger(__name__)


class TowerError(Exception):
    """The camera tower cannot be used right now."""

    user_error = True


class TowerDisconnected(TowerError):
    """The serial port is missing or stopped working."""


class TowerTimeout(TowerError):
    """The controller stopped answering, or a move or homing took too long."""


class TowerHomingError(TowerError):
    """The reference trigger did not fire within a turn."""


class TowerPositionError(TowerError):
    """The tower could not reach a heading, even after homing again."""


@dataclass(frozen=True)
class DepthFrame:
    depth: np.ndarray          # (H, W) depth along the optical axis, in units of ``scale_m``
    stamp_ns: int              # capture time on the host clock (time.time_ns)
    scale_m: float = 0.001     # RealSense z16: millimetres


class DepthCamera(Protocol):
    """A depth camera as the tower's source of frames: its intrinsics are known once open."""

    fx: float
    cx: float

    def open(self) -> None: ...

    def grab(self) -> DepthFrame: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Capture:
    """One view of a sweep: the camera heading reached, the frame and the odometry pose."""

    yaw_rad: float
    frame: DepthFrame
    pose: Pose | None


def steps_per_rev(full_steps: int = 200, microsteps: int = 16, gear_ratio: float = 1.0) -> int:
    """Microsteps per turn of the tower: motor full steps × microstepping × gear ratio."""
    n = full_steps * microsteps * gear_ratio
    if n < 4 or abs(n - round(n)) > 1e-9:
        raise TowerError(f"{full_steps} × {microsteps} × {gear_ratio} = {n} is not a whole "
                         "number of microsteps per turn")
    return round(n)


def assemble(captures: Sequence[Capture], fx: float, cx: float, beams: int = 360,
             max_range_m: float = 3.0, min_range_m: float = 0.2, rows: int = 1,
             compensate: bool = True) -> Sweep:
    """The pseudo-scan of a sweep's captures in the robot frame at the last capture's time."""
    if not captures:
        raise TowerError("a sweep without frames")
    ref = captures[-1]
    views = []
    for c in captures:
        origin = (0.0, 0.0, 0.0)
        if compensate and c.pose is not None and ref.pose is not None:
            x, y, th = between(ref.pose, c.pose).tolist()
            origin = (x, y, th)
        views.append(DepthView(c.yaw_rad, c.frame.depth, c.frame.scale_m, origin))
    return pseudo_scan(views, fx, cx, ref.frame.stamp_ns, beams, max_range_m, min_range_m, rows)


class Tower:
    """The tower's controller on ``port`` and the camera on it (a pseudo-scan source)."""

    def __init__(self, port: str, frame_source: Callable[[], DepthFrame],
                 odometry_at: Callable[[int], Pose | None], fx: float, cx: float,
                 steps_per_rev: int = 6400, headings_deg: Sequence[float] = (0, 90, 180, 270),
                 zero_offset_steps: int = 0, settle_s: float = 0.15, baud: int = 115200,
                 keepalive_s: float = 0.1, link_timeout_s: float = 1.0,
                 move_timeout_s: float = 5.0, home_timeout_s: float = 20.0,
                 beams: int = 360, max_range_m: float = 3.0, min_range_m: float = 0.2,
                 rows: int = 1, serial_factory: Callable[..., Any] = serial.Serial) -> None:
        if not headings_deg:
            raise TowerError("no camera headings configured")
        self.port, self.baud = port, baud
        self.frame_source, self.odometry_at = frame_source, odometry_at
        self.fx, self.cx = fx, cx
        self.steps_per_rev = steps_per_rev
        self.headings_deg = tuple(float(h) for h in headings_deg)
        self.zero_offset_steps = zero_offset_steps
        self.settle_s, self.keepalive_s = settle_s, keepalive_s
        self.link_timeout_s = link_timeout_s
        self.move_timeout_s, self.home_timeout_s = move_timeout_s, home_timeout_s
        self.beams, self.max_range_m, self.min_range_m, self.rows = (beams, max_range_m,
                                                                     min_range_m, rows)
        self.serial_factory = serial_factory
        self.counters: Counter[str] = Counter()
        self.homed = False
        self.home_count: int | None = None   # the count where the trigger last fired
        self.position: int | None = None
        self.state = ""
        self.last_captures: list[Capture] = []
        self._replies: queue.Queue[proto.Reply] = queue.Queue()
        self._io = threading.Lock()
        self._serial: Any = None
        self._last_write = 0.0
        self._last_valid = 0.0
        self._failure: TowerError | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reverse = False

    # -- lifetime ---------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, start the reader and keep-alive, home the tower (on failure the port
        is closed again and the error raised)."""
        try:
            self._serial = self.serial_factory(self.port, self.baud,
                                               timeout=self.keepalive_s / 2)
        except (serial.SerialException, OSError) as e:
            raise TowerDisconnected(f"cannot open {self.port}: {e}") from None
        self._failure = None
        self._stop.clear()
        self._last_valid = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True, name="tower")
        self._thread.start()
        try:
            self.home()
        except TowerError:
            self.close()
            raise

    def close(self) -> None:
        """Stop the tower where it is and close the port (the controller then de-energises on
        silence)."""
        if self._serial is not None and self._failure is None:
            try:
                self._write(proto.encode("STOP"))
            except TowerError as e:
                log.debug("tower: STOP not sent: %s", e)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    # -- the tower --------------------------------------------------------------------------
    def heading_steps(self, heading_deg: float) -> int:
        return self.zero_offset_steps + round(heading_deg / 360.0 * self.steps_per_rev)

    def home(self) -> int | None:
        """Home the tower; the count where the trigger fired (None if that report was lost)."""
        self.homed = False
        self._drain()
        self._write(proto.encode("HOME"))
        started = False
        deadline = time.monotonic() + self.home_timeout_s
        while True:
            r = self._next(deadline, "homing")
            if r.kind == "HOMED":
                self.home_count = r.ints[0]
                break
            if r.kind == "ACK" and r.word == "HOME":
                started = True
            elif r.kind == "ERR" and r.word == "NOTRIGGER":
                self.counters["homing_failures"] += 1
                raise TowerHomingError(
                    f"{self.port}: the reference trigger did not fire within {r.ints[0]} "
                    f"microsteps (a turn is {self.steps_per_rev}): check the optical switch, "
                    "its wiring and the steps per revolution")
            elif r.kind == "ERR" and r.word == "BUSY":
                self._write(proto.encode("STOP"))       # a move from before: stop, then home
                self._write(proto.encode("HOME"))
            elif r.kind == "ERR" and r.word == "BADCMD":
                self._write(proto.encode("HOME"))
            elif r.kind in ("PONG", "POS"):
                if r.word == "HOMING":
                    started = True
                elif started and r.word == "READY":     # HOMED was lost on the line
                    self.counters["lost_reports"] += 1
                    break
                elif started and r.word == "UNHOMED":   # its ERR NOTRIGGER was lost
                    self.counters["homing_failures"] += 1
                    raise TowerHomingError(f"{self.port}: homing ended without the "
                                           "reference trigger firing")
        self.homed = True
        self.position = 0
        self.counters["homes"] += 1
        log.info("tower homed: trigger at count %s", self.home_count)
        return self.home_count

    def move_to(self, steps: int) -> int:
        """Turn to ``steps`` (absolute microsteps) and return the position reached. A position
        error or a controller that lost its reference is homed again, and the move repeated
        once."""
        for _ in range(2):
            if not self.homed:
                self.home()
            problem = self._try_move(steps)
            if problem is None:
                self.position = steps
                return steps
            self.homed = False
            self.counters["rehomes"] += 1
            log.warning("tower: %s; homing again", problem)
        raise TowerPositionError(f"{self.port}: could not reach microstep {steps}, even after "
                                 "homing again")

    def _try_move(self, steps: int) -> str | None:
        """None when the move finished; otherwise why the tower needs homing."""
        self._drain()
        self._write(proto.encode("MOVE", steps))
        acked = False
        deadline = time.monotonic() + self.move_timeout_s
        while True:
            r = self._next(deadline, f"the move to microstep {steps}")
            if r.kind == "ACK" and r.word == "MOVE":
                acked = True
            elif r.kind == "DONE" and r.ints[0] == steps:
                return None
            elif r.kind in ("PONG", "POS") and r.word == "MOVING":
                acked = True
            elif r.kind in ("PONG", "POS") and acked and r.word == "READY" and r.ints[0] == steps:
                self.counters["lost_reports"] += 1       # DONE was lost on the line
                return None
            elif r.kind in ("PONG", "POS") and acked and r.word == "UNHOMED":
                return "the controller lost its reference"
            elif r.kind == "TIMEOUT":
                return "the controller stopped on silence"
            elif r.kind == "ERR":
                if r.word == "POSITION":
                    self.counters["position_errors"] += 1
                    return (f"position error: the trigger disagreed with count {r.ints[0]} "
                            "(lost steps)")
                if r.word == "NOTHOMED":
                    return "the controller is not homed"
                if r.word == "RANGE":
                    raise TowerPositionError(f"{self.port}: microstep {steps} is out of the "
                                             "controller's range")
                if r.word in ("BUSY", "BADCMD"):
                    if r.word == "BUSY":
                        self._write(proto.encode("STOP"))
                    self._write(proto.encode("MOVE", steps))

    def sweep(self) -> Sweep:
        """One pseudo-scan: a frame at each heading, merged in the robot frame of the last
        frame's capture time (the sweep's stamp)."""
        order = self.headings_deg[::-1] if self._reverse else self.headings_deg
        self._reverse = not self._reverse
        captures: list[Capture] = []
        for heading in order:
            reached = self.move_to(self.heading_steps(heading))
            time.sleep(self.settle_s)
            frame = self.frame_source()
            pose = self.odometry_at(frame.stamp_ns)
            if pose is None:
                self.counters["no_odometry"] += 1
            yaw = 2 * math.pi * (reached - self.zero_offset_steps) / self.steps_per_rev
            captures.append(Capture(yaw, frame, pose))
        self.last_captures = captures
        self.counters["sweeps"] += 1
        return assemble(captures, self.fx, self.cx, self.beams, self.max_range_m,
                        self.min_range_m, self.rows)

    # -- the line ---------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        with self._io:
            port = self._serial
            if port is None:
                raise TowerDisconnected(f"{self.port} is not open")
            try:
                port.write(data)
            except (serial.SerialException, OSError) as e:
                raise TowerDisconnected(f"{self.port}: write failed: {e}") from None
            self._last_write = time.monotonic()

    def _drain(self) -> None:
        while True:
            try:
                self._replies.get_nowait()
            except queue.Empty:
                return

    def _next(self, deadline: float, what: str) -> proto.Reply:
        while True:
            if self._failure is not None:
                raise self._failure
            now = time.monotonic()
            if now > deadline:
                raise TowerTimeout(f"{self.port}: {what} did not finish in time")
            if now - self._last_valid > self.link_timeout_s:
                raise TowerTimeout(f"{self.port}: no valid reply from the tower controller "
                                   f"for {self.link_timeout_s} s")
            try:
                return self._replies.get(timeout=min(0.05, max(deadline - now, 0.001)))
            except queue.Empty:
                continue

    def _run(self) -> None:
        splitter = proto.LineSplitter()
        port = self._serial
        try:
            while not self._stop.is_set():
                if time.monotonic() - self._last_write >= self.keepalive_s:
                    self._write(proto.encode("PING"))
                try:
                    data = port.read(max(port.in_waiting, 1))
                except (serial.SerialException, OSError) as e:
                    raise TowerDisconnected(f"{self.port}: read failed: {e}") from None
                overlong = splitter.overlong
                lines = splitter.feed(data)
                if splitter.overlong != overlong:
                    self._bad(f"{splitter.overlong - overlong} overlong line(s)")
                for line in lines:
                    try:
                        r = proto.parse_reply(line)
                    except proto.TowerProtocolError as e:
                        self._bad(str(e))
                        continue
                    self._last_valid = time.monotonic()
                    if r.kind in ("PONG", "POS", "DONE", "TIMEOUT"):
                        self.position = r.ints[0]
                    if r.kind in ("PONG", "POS"):
                        self.state = r.word
                    if r.kind == "TIMEOUT":
                        self.counters["controller_timeouts"] += 1
                        self.homed = False
                        log.warning("tower controller stopped on silence at count %d",
                                    r.ints[0])
                    self._replies.put(r)
        except TowerError as e:
            self.counters[f"tower_{type(e).__name__}"] += 1
            log.warning("tower: %s", e)
            self._failure = e

    def _bad(self, why: str) -> None:
        self.counters["bad_replies"] += 1
        n = self.counters["bad_replies"]
        if n <= 10 or n % 100 == 0:
            log.warning("tower: bad reply (%d so far): %s", n, why)


class TowerSource:
    """The tower as the agent's range sensor (``LidarSource``): pseudo-scans one after another
    in a thread of its own.

    The tower is opened (and homed) when the thread starts. A tower that fails (port lost,
    controller silent, homing failed, a heading not reached, the camera's frame source raising
    ``OSError`` or ``RuntimeError``) is closed, the failure counted (``tower_<Error>``) and
    logged once per new problem, and opened again every ``reconnect_s``: the agent keeps
    running, with no range sensor until the tower is back. ``open_camera`` and
    ``close_camera``, if given, go with each opening and closing of the tower (a camera
    unplugged with it is opened again with it)."""

    def __init__(self, tower: Tower, reconnect_s: float = 1.0,
                 open_camera: Callable[[], None] | None = None,
                 close_camera: Callable[[], None] | None = None) -> None:
        self.tower = tower
        self.reconnect_s = reconnect_s
        self.open_camera, self.close_camera = open_camera, close_camera
        self.counters: Counter[str] = Counter()
        self.connected = threading.Event()
        self.last_error = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, on_sweep: Callable[[Sweep], None]) -> None:
        self._thread = threading.Thread(target=self._run, args=(on_sweep,), daemon=True,
                                        name="tower-source")
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    def all_counters(self) -> dict[str, int]:
        return {**self.tower.counters, **self.counters}

    def _run(self, on_sweep: Callable[[Sweep], None]) -> None:
        while not self._stop.is_set():
            try:
                self._session(on_sweep)
            except (TowerError, OSError, RuntimeError) as e:
                self.connected.clear()             # cleared before the error is counted
                self.counters[f"tower_{type(e).__name__}"] += 1
                if str(e) != self.last_error:      # each new problem once, not every retry
                    log.warning("tower: %s; retrying every %g s", e, self.reconnect_s)
                    self.last_error = str(e)
            finally:
                self.connected.clear()
                self._shutdown()
            self._stop.wait(self.reconnect_s)

    def _session(self, on_sweep: Callable[[Sweep], None]) -> None:
        if self.open_camera is not None:
            self.open_camera()
        self.tower.open()
        self.connected.set()
        self.counters["connects"] += 1
        if self.last_error:
            log.info("tower on %s back", self.tower.port)
            self.last_error = ""
        while not self._stop.is_set():
            sweep = self.tower.sweep()
            self.counters["sweeps"] += 1
            on_sweep(sweep)

    def _shutdown(self) -> None:
        try:
            self.tower.close()
        except (TowerError, OSError) as e:        # the port may be gone already
            log.debug("tower: close: %s", e)
        if self.close_camera is not None:
            try:
                self.close_camera()
            except (OSError, RuntimeError) as e:
                log.debug("depth camera: close: %s", e)
