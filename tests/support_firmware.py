"""The motor-base firmware in the AVR simulator: building it, and a running board to test the
agent's real driver against (deploy/firmware/hil/hil_base.c prints what happens on the board's
pins and wire in simulated time; this module collects it)."""

from __future__ import annotations

import os
import shutil
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from robot_agent.drivers import base_protocol as proto
from tests.conftest import ROOT

FIRMWARE = ROOT / "deploy" / "firmware"
BUILD = FIRMWARE / "build"
ELF = BUILD / "base.elf"
HARNESS = BUILD / "hil_base"
#: what `make -C deploy/firmware` needs; deploy/bootstrap.sh installs it (root, dev extra)
TOOLS = ("avr-g++", "avr-objcopy", "avr-size", "avr-nm", "cc", "make")
HEADERS = (Path("/usr/include/simavr/sim_avr.h"), Path("/usr/include/gelf.h"))
PACKAGES = "gcc-avr avr-libc binutils-avr libsimavr-dev libelf-dev"


def require_toolchain() -> None:
    """Skip where the AVR toolchain and simavr are missing and cannot be installed (not root);
    as root `make test` installs them first, so there their absence is a failure."""
    missing = [t for t in TOOLS if shutil.which(t) is None]
    missing += [str(h) for h in HEADERS if not h.exists()]
    if not missing:
        return
    msg = f"the AVR toolchain / simavr is missing ({', '.join(missing)})"
    if os.geteuid() != 0:
        pytest.skip(f"{msg}: run `sudo apt-get install -y {PACKAGES}` (or `make test` as root)")
    pytest.fail(f"{msg}: `make venv` (deploy/bootstrap.sh all,dev) installs {PACKAGES}")


def make(*targets: str, **variables: str) -> subprocess.CompletedProcess[str]:
    args = ["make", "-C", str(FIRMWARE), *targets, *(f"{k}={v}" for k, v in variables.items())]
    return subprocess.run(args, capture_output=True, text=True, timeout=300)


def build() -> None:
    """The firmware image and the harness, as `make -C deploy/firmware all harness` builds them."""
    require_toolchain()
    out = make("all", "harness")
    assert out.returncode == 0, out.stdout + out.stderr
    assert ELF.exists() and HARNESS.exists()


# -- what the board did, in simulated time ---------------------------------------------------
@dataclass(frozen=True)
class WireFrame:
    t_first_us: int
    t_last_us: int
    raw: bytes

    def frame(self) -> proto.Frame | None:
        """The frame, or None where its checksum or length is wrong."""
        frames = proto.FrameParser().feed(self.raw)
        return frames[0] if frames else None


@dataclass(frozen=True)
class Sample:
    t_us: int
    drive: tuple[float, float]     # mean duty over the sample, wheel-forward sense
    speed: tuple[float, float]     # wheel ticks/s
    ticks: tuple[int, int]         # true wheel ticks


@dataclass(frozen=True)
class Report:
    t_us: int                      # simulated time the frame's first byte left the board
    enc: proto.Encoders


class Board:
    """The firmware running in hil_base, its serial port at ``link``."""

    def __init__(self, link: Path, *options: str) -> None:
        self.link = link
        self.rx: list[WireFrame] = []          # frames the board received
        self.tx: list[WireFrame] = []          # frames the board sent
        self.pins: list[tuple[int, str, int]] = []
        self.samples: list[Sample] = []
        self.info: list[str] = []
        self.stderr: list[str] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen([str(HARNESS), str(ELF), "--link", str(link), *options],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, bufsize=1)
        self._reader = threading.Thread(target=self._read, daemon=True, name="hil-out")
        self._reader.start()
        self._errors = threading.Thread(target=self._read_errors, daemon=True, name="hil-err")
        self._errors.start()
        assert self.wait(lambda: any(i.startswith("ready") for i in self.info), 30.0), \
            self.diagnostics()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            f = line.split()
            if not f:
                continue
            with self._lock:
                if f[0] == "M":
                    self.samples.append(Sample(int(f[1]), (float(f[2]), float(f[3])),
                                               (float(f[4]), float(f[5])),
                                               (int(f[6]), int(f[7]))))
                elif f[0] in ("RX", "TX"):
                    wf = WireFrame(int(f[1]), int(f[2]), bytes.fromhex(f[3]))
                    (self.rx if f[0] == "RX" else self.tx).append(wf)
                elif f[0] == "P":
                    self.pins.append((int(f[1]), f[2], int(f[3])))
                elif f[0] == "I":
                    self.info.append(" ".join(f[1:]))

    def _read_errors(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.stderr.append(line.rstrip())

    def diagnostics(self) -> str:
        return (f"harness exit {self.proc.poll()}; info {self.info[-10:]}; "
                f"stderr {self.stderr[-10:]}")

    def command(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def wait(self, cond: Callable[[], bool], timeout_s: float = 60.0) -> bool:
        """Whether ``cond()`` becomes true; the wall-clock timeout only ends a hung run."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            if cond():
                return True
            if self.proc.poll() is not None:
                return cond()
            time.sleep(0.01)
        return cond()

    def now_us(self) -> int:
        with self._lock:
            return self.samples[-1].t_us if self.samples else 0

    def run_for(self, sim_s: float, tick: Callable[[], None] | None = None) -> None:
        """Let ``sim_s`` seconds of simulated time pass, calling ``tick`` every 0.1 s of wall
        time meanwhile (a driver's caller renewing its command, as the server's controller does)."""
        end = self.now_us() + int(sim_s * 1e6)
        t0 = time.monotonic()
        while self.now_us() < end:
            assert self.proc.poll() is None, self.diagnostics()
            assert time.monotonic() - t0 < 60 + 20 * sim_s, "the simulation hung"
            if tick is not None:
                tick()
            time.sleep(0.1)

    def reports(self) -> list[Report]:
        """The ENCODERS frames the board sent, with valid checksums."""
        out = []
        with self._lock:
            tx = list(self.tx)
        for wf in tx:
            f = wf.frame()
            if f is not None and f.kind == proto.ENCODERS:
                out.append(Report(wf.t_first_us, proto.parse_encoders(f)))
        return out

    def received(self) -> list[tuple[int, proto.Frame | None]]:
        """(time of the last byte, frame or None where it was bad) for each frame received."""
        with self._lock:
            rx = list(self.rx)
        return [(wf.t_last_us, wf.frame()) for wf in rx]

    def samples_between(self, t0_us: int, t1_us: int) -> list[Sample]:
        with self._lock:
            return [s for s in self.samples if t0_us <= s.t_us < t1_us]

    def stopped_at(self, side: str, after_us: int) -> int | None:
        """Simulated time both direction pins of ``side`` ("L"/"R") were low, at or after
        ``after_us``: the motor is no longer driven."""
        with self._lock:
            pins = list(self.pins)
        level = {f"{side}_IN1": 0, f"{side}_IN2": 0}
        before = [p for p in pins if p[0] < after_us and p[1] in level]
        for _, name, v in before:
            level[name] = v
        if not any(level.values()):
            return after_us
        for t, name, v in pins:
            if t < after_us or name not in level:
                continue
            level[name] = v
            if not any(level.values()):
                return t
        return None

    def info_time(self, prefix: str) -> int:
        """The simulated time in the last info line starting with ``prefix``."""
        with self._lock:
            lines = [i for i in self.info if i.startswith(prefix)]
        assert lines, f"no '{prefix}' in {self.info}"
        return int(lines[-1].split()[-1])

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.command("quit")
                self.proc.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=10)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
