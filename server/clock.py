"""Robot clocks against the server's: each robot's stamps mapped into server time.

Robots stamp with their own clocks, and those clocks step: NTP corrects them, a Raspberry Pi
without a battery-backed clock boots in 1970 and jumps to the present once the network is up.
The server keeps one offset per robot (server time − robot time, 0 to start with) and maps
every stamp by it:

- a mapped stamp within ``max_skew_s`` of the server's clock when it arrived, and after the
  robot's last accepted stamp on that stream, is accepted;
- otherwise the message is refused (``clock-skew`` or ``out-of-order``) and remembered as a
  possible step: when ``rebase_after`` messages in a row agree on one new offset, the robot's
  clock has stepped; the offset is re-based to it (logged and counted) and the robot is
  served again. A lone stamp far off (a glitch, or a stranger's message) is only refused.

Mapped stamps therefore never run more than ``max_skew_s`` ahead of the server's clock, and
each robot's mapped stamps only go forward, so its graph stays consistent across a step.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


class StampRefused(ValueError):
    """A stamp the server will not use; ``reason`` is ``clock-skew`` or ``out-of-order``."""

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}")


@dataclass(frozen=True)
class ClockPolicy:
    max_skew_ns: int = 2_000_000_000
    rebase_after: int = 3

    @property
    def min_step_ns(self) -> int:
        """Smaller offset changes are jitter, repeats or reordering, not a step of the clock."""
        return self.max_skew_ns // 10


@dataclass
class RobotClock:
    """One robot's offset to the server's clock and its last accepted stamp per stream."""

    policy: ClockPolicy
    offset_ns: int = 0
    steps: int = 0                  # how often the offset was re-based
    last_ns: dict[str, int] = field(default_factory=dict)
    _candidate_ns: int | None = None
    _agreeing: int = 0

    def map(self, stream: str, stamp_ns: int, server_ns: int | None) -> int:
        """The stamp in server time, or StampRefused. ``server_ns`` is the server's clock when
        the message arrived (None: no clock to check against; only the order is checked)."""
        t = stamp_ns + self.offset_ns
        last = self.last_ns.get(stream)
        skewed = server_ns is not None and abs(t - server_ns) > self.policy.max_skew_ns
        if not skewed and (last is None or t > last):
            self._candidate_ns, self._agreeing = None, 0
            self.last_ns[stream] = t
            return t
        if server_ns is not None and self._step_confirmed(server_ns - stamp_ns):
            old, self.offset_ns = self.offset_ns, server_ns - stamp_ns
            self.steps += 1
            self._candidate_ns, self._agreeing = None, 0
            t = stamp_ns + self.offset_ns
            if last is None or t > last:
                self.last_ns[stream] = t
                return t
            raise StampRefused("out-of-order", f"re-based by {(self.offset_ns - old) / 1e9:+.3f}"
                               f" s, {stream} stamp still not after the last accepted")
        if skewed:
            assert server_ns is not None
            raise StampRefused("clock-skew", f"{stream} stamp {(t - server_ns) / 1e9:+.3f} s "
                               "from the server's clock")
        raise StampRefused("out-of-order", f"{stream} stamp {(t - (last or 0)) / 1e9:+.3f} s "
                           "before the last accepted")

    def _step_confirmed(self, offset_ns: int) -> bool:
        """Count messages in a row that agree on ``offset_ns``; True once there are enough."""
        if abs(offset_ns - self.offset_ns) <= self.policy.min_step_ns:
            self._candidate_ns, self._agreeing = None, 0
            return False
        c = self._candidate_ns
        if c is not None and abs(offset_ns - c) <= self.policy.max_skew_ns:
            self._agreeing += 1
        else:
            self._candidate_ns, self._agreeing = offset_ns, 1
        return self._agreeing >= self.policy.rebase_after


class ServerClock:
    """The server's own time: this machine's clock (``wall``), the simulator's (``sim``, fed
    by ``on_sim_clock``), or the newest robot stamp accepted (``stamps``, for replays)."""

    def __init__(self, source: str = "wall") -> None:
        if source not in ("wall", "sim", "stamps"):
            raise ValueError(f"unknown clock source {source!r}")
        self.source = source
        self._latest_ns: int | None = None

    def reference_ns(self) -> int | None:
        """What robot stamps are checked against (None: nothing to check against yet)."""
        if self.source == "wall":
            return time.time_ns()
        return self._latest_ns if self.source == "sim" else None

    def now_ns(self) -> int:
        """The time periodic work runs on (0 before a sim or stamp clock has started)."""
        ref = self.reference_ns()
        return ref if ref is not None else (self._latest_ns or 0)

    def on_sim_clock(self, stamp_ns: int) -> None:
        if self.source == "sim":
            self._latest_ns = max(self._latest_ns or 0, stamp_ns)

    def on_accepted(self, stamp_ns: int) -> None:
        if self.source == "stamps":
            self._latest_ns = max(self._latest_ns or 0, stamp_ns)
