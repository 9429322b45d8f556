"""Admission of robots and their messages: who may talk to the server, when, and in what order.

A message is refused (with a typed reason, counted per reason and logged at a limited rate)
when its key names a different robot than its body (``key-mismatch``), when the robot is not
on the configured allowlist (``unknown-robot``), when its stamp is far ahead of its own receipt
or does not advance (``clock-skew``, ``out-of-order``; see ``server.runtime.clock``). Refusing is
never fatal: the message is dropped, everything accepted before stays.

A robot that is not yet known is admitted as soon as its agent's liveliness token is seen, or
once it has sent ``probation`` messages with sane stamps. Until then its messages are held
(not processed, not lost) and released in order on admission. A burst of one-message ids, as
a stranger or a broken client sends, therefore costs a small record each, and those records
go when their ids have been silent (and not alive) for ``forget_after_s``, or, beyond
``max_newcomers`` waiting at once, oldest first. Records of robots that left go after the same
silence; such a robot starts afresh when it comes back (e.g. after a reboot).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from schemas.ratelog import RateLimitedLog
from server.runtime.clock import Again, ClockPolicy, RobotClock, StampRefused

log = logging.getLogger(__name__)


class Refused(ValueError):
    """A message the server will not use; ``reason`` is a short machine-readable tag."""

    def __init__(self, robot_id: str, reason: str, detail: str) -> None:
        self.robot_id = robot_id
        self.reason = reason
        super().__init__(f"{robot_id}: {reason}: {detail}")


@dataclass(frozen=True)
class AdmissionPolicy:
    allowed: frozenset[str] | None = None   # None: any robot id
    probation: int = 3                      # messages that admit a robot without a token
    forget_after_ns: int = 60_000_000_000
    max_newcomers: int = 10_000             # ids waiting for admission at once
    newcomers_per_s: float = 2.0            # admissions by probation alone, at most this fast
    newcomer_burst: int = 10                # ... after this many at once
    clock: ClockPolicy = field(default_factory=ClockPolicy)


@dataclass
class RobotRecord:
    robot_id: str
    clock: RobotClock
    alive: bool = False
    admitted: bool = False
    last_heard_ns: int = 0                  # the server's clock when it last heard of it
    #: (stream, stamp in server time, message) held while on probation
    held: list[tuple[str, int, Any]] = field(default_factory=list)
    accepted: Counter[str] = field(default_factory=Counter)
    #: the latest clock steps: (the server's clock at the re-base [ns], the step [ns])
    rebased: list[tuple[int, int]] = field(default_factory=list)


class RobotRegistry:
    """Robots heard of on the bus: admission, liveliness, clock offsets and stream order."""

    def __init__(self, policy: AdmissionPolicy | None = None) -> None:
        self.policy = policy or AdmissionPolicy()
        self.robots: dict[str, RobotRecord] = {}
        self.refused: Counter[str] = Counter()           # by reason, all ids
        self.refused_by_robot: Counter[tuple[str, str]] = Counter()  # (robot, reason), bounded
        self.joined = self.forgotten = self.clock_steps = 0
        self._waiting: dict[str, None] = {}   # ids not admitted yet, oldest first
        self.evicted = 0
        self.held_dropped = 0        # held messages of newcomers waiting for their turn
        self._log = RateLimitedLog(log)
        self._allowance = float(self.policy.newcomer_burst)   # newcomers that may join now
        self._allowance_ns: int | None = None

    # -- messages --------------------------------------------------------------------------
    def admit(self, key_robot_id: str | None, robot_id: str, stream: str, stamp_ns: int,
              server_ns: int | None, message: Any = None, slack_ns: int = 0,
              again: Again | None = None) -> list[tuple[str, int, Any]]:
        """Admit one message; returns what is now ready for processing, in order, as
        (stream, stamp in server time, message): nothing while the robot is on probation,
        its held messages and this one when it is admitted. ``server_ns`` is the server's
        clock when the message arrived, known to ``slack_ns`` (``again`` tells it once more,
        later: ``RobotClock.map``). Raises Refused."""
        if key_robot_id is not None and key_robot_id != robot_id:
            raise self._refuse(robot_id, "key-mismatch",
                               f"published under robot {key_robot_id!r}'s key")
        p = self.policy
        if p.allowed is not None and robot_id not in p.allowed:
            raise self._refuse(robot_id, "unknown-robot", "not in the configured robot list")
        rec = self.robots.get(robot_id) or self._new(robot_id)
        steps, offset = rec.clock.steps, rec.clock.offset_ns
        try:
            t = rec.clock.map(stream, stamp_ns, server_ns, slack_ns, again)
        except StampRefused as e:
            raise self._refuse(robot_id, e.reason, str(e).split(": ", 1)[1]) from None
        finally:
            if server_ns is not None:
                rec.last_heard_ns = server_ns
        if server_ns is None:   # no clock of its own (replays): the stamps are the time
            rec.last_heard_ns = max(rec.last_heard_ns, t)
        if rec.clock.steps != steps:
            self.clock_steps += 1
            rec.rebased = [*rec.rebased[-9:], (server_ns or t, offset - rec.clock.offset_ns)]
            log.warning("robot %s: its clock stepped by %+.3f s; stamps re-based (step #%d)",
                        robot_id, (offset - rec.clock.offset_ns) / 1e9, rec.clock.steps)
        elif rec.clock.offset_ns != offset:
            self._log.info("clock-adjusted", "robot %s: offset to the server's clock adjusted "
                           "by %+.3f s", robot_id, (rec.clock.offset_ns - offset) / 1e9)
        rec.accepted[stream] += 1
        if rec.admitted:
            return [(stream, t, message)]
        rec.held.append((stream, t, message))
        if rec.alive:
            return self._admit(rec)
        if len(rec.held) >= p.probation:
            if self._newcomer_may_join(server_ns):
                return self._admit(rec)
            if len(rec.held) > p.probation:   # waiting for its turn: only the latest are kept
                del rec.held[0]
                self.held_dropped += 1
        return []

    def _newcomer_may_join(self, server_ns: int | None) -> bool:
        """A token bucket: ``newcomer_burst`` at once, then ``newcomers_per_s``. (Replays,
        without a clock of their own, are not limited.)"""
        p = self.policy
        if server_ns is None:
            return True
        if self._allowance_ns is not None:
            earned = (server_ns - self._allowance_ns) / 1e9 * p.newcomers_per_s
            self._allowance = min(float(p.newcomer_burst), self._allowance + max(0.0, earned))
        self._allowance_ns = server_ns
        if self._allowance < 1.0:
            return False
        self._allowance -= 1.0
        return True

    def _new(self, robot_id: str, waiting: bool = True) -> RobotRecord:
        """A record for a robot not heard of before (``waiting``: not admitted yet)."""
        rec = self.robots[robot_id] = RobotRecord(robot_id, RobotClock(self.policy.clock))
        if not waiting:
            return rec
        if len(self._waiting) >= self.policy.max_newcomers:
            # the oldest newcomer goes: a real robot admits itself within a few messages,
            # so a flood of new ids cannot keep it out
            oldest = next(iter(self._waiting))
            del self._waiting[oldest], self.robots[oldest]
            self.evicted += 1
            self._log.warning("evicted", "newcomer %s dropped: %d robot ids are waiting to be "
                              "admitted", oldest, len(self._waiting) + 1)
        self._waiting[robot_id] = None
        return rec

    def _admit(self, rec: RobotRecord) -> list[tuple[str, int, Any]]:
        rec.admitted = True
        self._waiting.pop(rec.robot_id, None)
        self.joined += 1
        self._log.info("joined", "robot %s joined%s", rec.robot_id,
                       "" if rec.alive else " (no liveliness token seen)")
        held, rec.held = rec.held, []
        return held

    def trusted(self, robot_id: str) -> bool:
        """Served ahead of newcomers: named in the configuration, or holding a liveliness
        token."""
        if self.policy.allowed is not None:
            return robot_id in self.policy.allowed
        rec = self.robots.get(robot_id)
        return rec is not None and rec.alive

    # -- liveliness and forgetting -----------------------------------------------------------
    def set_alive(self, robot_id: str, alive: bool, server_ns: int | None = None
                  ) -> tuple[bool, list[tuple[str, int, Any]]]:
        """Record liveliness; returns (changed, messages released by admission)."""
        p = self.policy
        if p.allowed is not None and robot_id not in p.allowed:
            return False, []
        rec = self.robots.get(robot_id)
        if rec is None:
            if not alive:
                return False, []
            rec = self._new(robot_id, waiting=False)
        if server_ns is not None:
            rec.last_heard_ns = server_ns
        changed = rec.alive != alive
        rec.alive = alive
        return changed, self._admit(rec) if alive and not rec.admitted else []

    def forget_silent(self, server_ns: int) -> list[str]:
        """Drop the records of robots that are not alive and were last heard of more than
        ``forget_after_s`` ago; returns the ids of those that had been admitted."""
        cutoff = server_ns - self.policy.forget_after_ns
        gone = [r for r in self.robots.values() if not r.alive and r.last_heard_ns < cutoff]
        for r in gone:
            del self.robots[r.robot_id]
            self._waiting.pop(r.robot_id, None)
        self.forgotten += len(gone)
        left = [r.robot_id for r in gone if r.admitted]
        if gone:
            self._log.info("forgotten", "forgot %d silent robot ids (%d had joined: %s)",
                           len(gone), len(left), ", ".join(left[:10]))
        return left

    # -- counting --------------------------------------------------------------------------
    def _refuse(self, robot_id: str, reason: str, detail: str) -> Refused:
        self.refused[reason] += 1
        if robot_id in self.robots or len(self.refused_by_robot) < 1000:
            self.refused_by_robot[(robot_id, reason)] += 1
        err = Refused(robot_id, reason, detail)
        self._log.warning(reason, "refused message #%d: %s", self.refused[reason], err)
        return err

    def counters(self) -> dict[str, Any]:
        """Per robot (accepted and refused by kind, clock steps) and fleet-wide totals."""
        out: dict[str, Any] = {}
        for (rid, reason), n in self.refused_by_robot.items():
            out.setdefault(rid, {})[f"refused_{reason}"] = n
        for rid, r in self.robots.items():
            d = out.setdefault(rid, {})
            d.update({f"accepted_{k}": v for k, v in r.accepted.items()})
            if r.clock.steps:
                d["clock_steps"] = r.clock.steps
                d["clock_rebased"] = [[at / 1e9, step / 1e9] for at, step in r.rebased]
            if r.clock.adjustments:
                d["clock_adjustments"] = r.clock.adjustments
            if r.clock.at_receipt:
                d["clock_taken_at_receipt"] = r.clock.at_receipt
            if r.clock.offset_ns:
                d["clock_offset_s"] = r.clock.offset_ns / 1e9
        return out

    def totals(self) -> dict[str, Any]:
        return {"refused": dict(self.refused), "joined": self.joined,
                "forgotten": self.forgotten, "evicted_newcomers": self.evicted,
                "held_dropped": self.held_dropped,
                "clock_steps": self.clock_steps, "known": len(self.robots),
                "on_probation": len(self._waiting)}
