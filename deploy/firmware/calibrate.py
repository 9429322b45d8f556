"""Measure the motor base's wheels for the firmware's speed-control constants.

    .venv/bin/python deploy/firmware/calibrate.py --port /dev/mrslam-base

WHEELS OFF THE GROUND. It asks for a speed no wheel can reach, so the firmware drives both
motors at full duty for a second, then stops them; from the board's encoder reports it prints
each wheel's full-duty speed and time constant, and the constants to set at the top of
deploy/firmware/base/base.ino (deploy/firmware/README.md, "Calibrating"). Stop the agent first:
the port takes one user.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time

import serial

from robot_agent.drivers import base_protocol as proto

BEYOND_REACH = 1_000_000        # ticks/s: the PI saturates at full duty


def read_reports(port: serial.Serial, parser: proto.FrameParser) -> list[proto.Encoders]:
    return [proto.parse_encoders(f) for f in parser.feed(port.read(max(port.in_waiting, 1)))
            if f.kind == proto.ENCODERS]


def step_response(port: serial.Serial, seconds: float) -> list[proto.Encoders]:
    """Reports from 0.2 s at rest, ``seconds`` at full duty forward, and 0.3 s after STOP."""
    parser = proto.FrameParser()
    seq = 0
    reports: list[proto.Encoders] = []
    port.write(proto.stop_frame(seq))
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.2:
        reports += read_reports(port, parser)
    t1 = time.monotonic()
    next_renewal = 0.0
    while time.monotonic() - t1 < seconds:
        if time.monotonic() >= next_renewal:
            seq += 1
            port.write(proto.speed_frame(seq, BEYOND_REACH, BEYOND_REACH, 300))
            next_renewal = time.monotonic() + 0.05
        reports += read_reports(port, parser)
    port.write(proto.stop_frame(seq + 1))
    t2 = time.monotonic()
    while time.monotonic() - t2 < 0.3:
        reports += read_reports(port, parser)
    return reports


def analyse(reports: list[proto.Encoders], side: int) -> tuple[float, float]:
    """(full-duty speed [ticks/s], time constant [s]) of one wheel (0 left, 1 right)."""
    driving = [i for i, r in enumerate(reports) if r.flags & proto.FLAG_DRIVING]
    if len(driving) < 10:
        raise SystemExit("the board never reported driving: is the port right, the firmware on?")
    first, last = driving[0], driving[-1]
    ticks = [(r.left_ticks, r.right_ticks)[side] for r in reports]
    times = [r.time_ms for r in reports]
    # speed over each report interval, placed at the interval's middle [s after the start]
    speeds = []
    for i in range(first + 1, last + 1):
        dt = ((times[i] - times[i - 1]) % 2**32) / 1000
        mid = ((times[i] - times[first]) % 2**32) / 1000 - dt / 2
        speeds.append((mid, proto.tick_delta(ticks[i], ticks[i - 1]) / dt))
    tail = [v for t, v in speeds if t >= speeds[-1][0] - 0.3]
    full = sum(tail) / len(tail)
    # time to 63 % of the full speed, interpolated between reports
    tau = float("nan")
    for (ta, va), (tb, vb) in itertools.pairwise(speeds):
        if abs(vb) >= 0.632 * abs(full) > abs(va):
            tau = ta + (0.632 * abs(full) - abs(va)) / (abs(vb) - abs(va)) * (tb - ta)
            break
    return full, tau


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", default="/dev/mrslam-base")
    ap.add_argument("--seconds", type=float, default=1.0, help="time at full duty")
    args = ap.parse_args(argv)
    with serial.Serial(args.port, 115200, timeout=0.02) as port:
        reports = step_response(port, args.seconds)
    results = [analyse(reports, side) for side in (0, 1)]
    for name, (full, tau) in zip(("left", "right"), results, strict=True):
        print(f"{name}: full duty {full:.0f} ticks/s, time constant {tau:.3f} s")
    backwards = [name for name, (full, _) in zip(("left", "right"), results, strict=True)
                 if full < 0]
    if backwards:
        print(f"the ticks of {', '.join(backwards)} went down: if that wheel turned backwards, "
              "flip its sign (L_SIGN / R_SIGN); if it turned forwards, swap its encoder's A "
              "and B wires", file=sys.stderr)
        return 1
    fastest = max(full for full, _ in results)
    tau = max(t for _, t in results)
    print(f"const float KFF = 1.0f / {fastest:.0f}.0f, TAU_S = {tau:.2f}f, "
          f"KP = {0.8 / fastest:.6f}f, KI = {8 / fastest:.6f}f;")
    return 0


if __name__ == "__main__":
    sys.exit(main())
