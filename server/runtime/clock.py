"""Robot clocks against the server's: each robot's stamps mapped into server time.

Robots stamp with their own clocks, and those clocks are off and step: NTP corrects them, a
Raspberry Pi without a battery-backed clock boots in 1970 and jumps to the present once the
network is up. Networks, meanwhile, are late: a Wi-Fi link that roams between access points
holds a robot's messages for seconds and then delivers them in a burst.

The server keeps one offset per robot (server time − robot time) by passive synchronisation
(E. Olson, "A passive solution to the sensor synchronization problem", IROS 2010): every
message gives ``d = receive − stamp``, which is the true offset plus the message's delay, and
delay is never negative. So the true offset is at most the smallest ``d`` seen, and a delay
burst only adds to ``d``: it can never move the estimate. Here:

- the first message sets the offset: 0 when its ``d`` is within ``max_skew`` (a clock that
  is set is trusted, and a first message that came late does not set it wrong; the rules
  below correct it if it was not), else its ``d``;
- the offset follows the minimum of ``d`` over the messages received in the last ``window``,
  with a dead band of ``tolerance``: it moves only when it is more than that off;
- a stamp ahead of its own receipt by more than ``tolerance`` cannot be explained by delay: the
  robot's clock jumped forward (or the message is not the robot's). ``rebase_after`` such
  messages in a row that agree re-base the offset at once; until then each is taken at its
  receive time, or refused (``clock-skew``) when it is more than ``max_skew`` ahead;
- a stamp not after the robot's last one on the same stream cannot be explained by delay
  either (a stream arrives in order): the clock stepped back, or the message is stale or
  forged. It is refused (``out-of-order``), and ``rebase_after`` in a row that agree re-base;
- a clock that stepped back while the robot was silent shows as every message being late; the
  window's minimum rises once the messages from before the step have left the window. It is
  only taken from a window whose messages were received over at least half its length, which
  a burst released at once never is.

Mapped stamps never run more than ``tolerance`` ahead of their receipt, and each stream's
mapped stamps only go forward, so a robot's graph stays consistent across a step.

The receive time is the server's clock when the message's bytes reached it: the router stamps
every sample as it arrives, in Zenoh's own threads (``Bus.subscribe_received``), so the
server's own stalls (a long merge, a snapshot, a garbage collection) are not taken for the
robots' delay.
"""

from __future__ import annotations

import bisect
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


#: a message's receipt, told again later (None: no clock)
Again = Callable[[], "int | None"]


class StampRefused(ValueError):
    """A stamp the server will not use; ``reason`` is ``clock-skew`` or ``out-of-order``."""

    def __init__(self, reason: str, detail: str) -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}")


@dataclass(frozen=True)
class ClockPolicy:
    max_skew_ns: int = 2_000_000_000
    rebase_after: int = 3
    window_ns: int = 10_000_000_000
    tolerance_ns: int = 50_000_000

    @property
    def min_step_ns(self) -> int:
        """Re-bases larger than this are clock steps (logged and counted as such); smaller
        ones are adjustments (drift, a slower link)."""
        return self.max_skew_ns // 10


@dataclass
class RobotClock:
    """One robot's offset to the server's clock and its last stamps per stream."""

    policy: ClockPolicy
    offset_ns: int = 0
    steps: int = 0                  # re-bases larger than ``min_step_ns``
    adjustments: int = 0            # smaller ones
    at_receipt: int = 0             # messages ahead of their receipt, taken at it
    last_ns: dict[str, int] = field(default_factory=dict)      # mapped, per stream
    last_raw_ns: dict[str, int] = field(default_factory=dict)  # the robot's own, per stream
    _started: bool = False
    #: (receive, d) received within the window: all of them, and the increasing minima
    _recent: deque[int] = field(default_factory=deque)
    _minima: deque[tuple[int, int]] = field(default_factory=deque)
    #: messages in a row that disagree with the offset (d, stamp, receipt told again), and
    #: which way ("ahead"/"back")
    _candidates: list[tuple[int, int, Again | None]] = field(default_factory=list)
    _direction: str = ""

    def map(self, stream: str, stamp_ns: int, received_ns: int | None, slack_ns: int = 0,
            again: Again | None = None) -> int:
        """The stamp in server time, or StampRefused. ``received_ns`` is the server's clock
        when the message arrived (None: no clock to check against; only the order is
        checked); it may be up to ``slack_ns`` later than that (a simulation may hand over its
        clock message after the message it preceded). ``again`` tells the receipt once more,
        later, when the server may know it better: a re-base is taken from it."""
        last_raw = self.last_raw_ns.get(stream)
        if received_ns is None:
            if last_raw is not None and stamp_ns <= last_raw:
                raise StampRefused("out-of-order", f"{stream} stamp "
                                   f"{(stamp_ns - last_raw) / 1e9:+.3f} s before the last")
            return self._accept(stream, stamp_ns, stamp_ns)
        d = received_ns - stamp_ns
        if not self._started:
            self._started = True
            self.offset_ns = 0 if abs(d) <= self.policy.max_skew_ns + slack_ns else d
        if last_raw is not None and stamp_ns <= last_raw:
            if self._confirmed(d, stamp_ns, again, "back"):
                self._rebase(received_ns)
                return self._accept(stream, stamp_ns, stamp_ns + self.offset_ns)
            raise StampRefused("out-of-order", f"{stream} stamp "
                               f"{(stamp_ns - last_raw) / 1e9:+.3f} s before the last")
        ahead = self.offset_ns - d
        if ahead > self.policy.tolerance_ns + slack_ns:
            if self._confirmed(d, stamp_ns, again, "ahead"):
                self._rebase(received_ns)
                return self._accept(stream, stamp_ns, stamp_ns + self.offset_ns)
            if ahead > self.policy.max_skew_ns:
                raise StampRefused("clock-skew", f"{stream} stamp {ahead / 1e9:+.3f} s ahead "
                                   "of its receipt")
            # taken no later than it came; its stamp is not trusted to order the next ones
            self.at_receipt += 1
            return self._accept(stream, None, received_ns + slack_ns)
        self._candidates.clear()
        self._remember(received_ns, d)
        self._follow_minimum(received_ns)
        return self._accept(stream, stamp_ns, stamp_ns + self.offset_ns)

    def _accept(self, stream: str, stamp_ns: int | None, mapped_ns: int) -> int:
        last = self.last_ns.get(stream)
        if last is not None and mapped_ns <= last:
            mapped_ns = last + 1    # an offset that moved down a little never reorders
        self.last_ns[stream] = mapped_ns
        if stamp_ns is not None:
            self.last_raw_ns[stream] = stamp_ns
        return mapped_ns

    def _confirmed(self, d: int, stamp_ns: int, again: Again | None, direction: str) -> bool:
        """Count messages in a row that disagree with the offset the same way and agree with
        each other on a new one; True once there are ``rebase_after`` of them."""
        p = self.policy
        if direction == "back" and abs(d - self.offset_ns) <= p.tolerance_ns:
            self._candidates.clear()  # a repeat or a reordering, not a step of the clock
            return False
        c = self._candidates
        if c and (direction != self._direction or abs(d - c[0][0]) > p.max_skew_ns):
            c.clear()
        self._direction = direction
        c.append((d, stamp_ns, again))
        return len(c) >= p.rebase_after

    def _rebase(self, received_ns: int) -> None:
        """The offset to the smallest d of the messages that confirmed a step; the window
        starts over from them (what came before the step says nothing about the clock now)."""
        told = [(again(), stamp) if again is not None else (None, stamp)
                for _, stamp, again in self._candidates]
        ds = [d if t is None else t - stamp for (d, _, _), (t, stamp) in zip(
            self._candidates, told, strict=True)]
        new = min(ds)
        self._recent.clear()
        self._minima.clear()
        for d in ds:
            self._remember(received_ns, d)
        self._candidates.clear()
        self.last_raw_ns.clear()
        self._set(new)

    def _remember(self, received_ns: int, d: int) -> None:
        self._recent.append(received_ns)
        m = self._minima
        while m and m[-1][1] >= d:
            m.pop()
        m.append((received_ns, d))
        start = received_ns - self.policy.window_ns
        while self._recent and self._recent[0] < start:
            self._recent.popleft()
        while m and m[0][0] < start:
            m.popleft()

    def _follow_minimum(self, received_ns: int) -> None:
        """Raise the offset to the window's minimum when every message in it came later than
        the offset says, and they came over at least half the window."""
        p = self.policy
        if not self._minima or received_ns - self._recent[0] < p.window_ns // 2:
            return
        low = self._minima[0][1]
        if low - self.offset_ns > p.tolerance_ns:
            self._set(low)

    def _set(self, offset_ns: int) -> None:
        change = offset_ns - self.offset_ns
        self.offset_ns = offset_ns
        if abs(change) > self.policy.min_step_ns:
            self.steps += 1
        else:
            self.adjustments += 1


class ServerClock:
    """The server's own time: this machine's clock (``wall``), the simulator's (``sim``, fed
    by ``on_sim_clock``), or the newest robot stamp accepted (``stamps``, for replays)."""

    #: simulator clock messages kept to place a receipt in simulated time
    HISTORY = 64

    def __init__(self, source: str = "wall") -> None:
        if source not in ("wall", "sim", "stamps"):
            raise ValueError(f"unknown clock source {source!r}")
        self.source = source
        self._latest_ns: int | None = None
        #: (receipt on this machine's clock, simulated time, step, real-time factor), by receipt
        self._sim: list[tuple[int, int, int, float]] = []

    def reference_ns(self) -> int | None:
        """The server's clock now (None: nothing to check against yet)."""
        if self.source == "wall":
            return time.time_ns()
        return self._latest_ns if self.source == "sim" else None

    def receive_ns(self, wall_ns: int) -> tuple[int | None, int]:
        """The server's clock at a receipt stamped ``wall_ns`` on this machine's clock, and
        how well it is known [ns]. In a simulation it is the simulated time then, from the
        clock messages received before it (their own receipts order them, whichever callback
        ran first); in lockstep only the step is known. None: no clock to check against."""
        if self.source != "sim":
            return (wall_ns if self.source == "wall" else None), 0
        h = self._sim
        i = bisect.bisect_right(h, wall_ns, key=lambda e: e[0]) - 1
        if i < 0:
            return self._latest_ns, 0
        at_ns, sim_ns, dt_ns, rtf = h[i]
        if rtf <= 0.0:
            # lockstep: simulated time stands while the agents answer, and the next step's
            # clock message may not have been handed to us yet
            return sim_ns, dt_ns
        # the next step's clock message may have come before this one and not yet been
        # handed over (a simulation catching up publishes faster than real time)
        newest = i == len(h) - 1
        return (sim_ns + min(round((wall_ns - at_ns) * rtf), 10 * dt_ns),
                dt_ns if newest else 0)

    def now_ns(self) -> int:
        """The time periodic work runs on (0 before a sim or stamp clock has started)."""
        ref = self.reference_ns()
        return ref if ref is not None else (self._latest_ns or 0)

    def on_sim_clock(self, stamp_ns: int, received_ns: int | None = None, dt_ns: int = 0,
                     real_time_factor: float = 0.0) -> None:
        if self.source != "sim":
            return
        self._latest_ns = max(self._latest_ns or 0, stamp_ns)
        if received_ns is not None:
            entry = (received_ns, stamp_ns, dt_ns, real_time_factor)
            bisect.insort(self._sim, entry, key=lambda e: e[0])
            del self._sim[:-self.HISTORY]

    def on_accepted(self, stamp_ns: int) -> None:
        if self.source == "stamps":
            self._latest_ns = max(self._latest_ns or 0, stamp_ns)
