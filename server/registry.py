"""Admission of robots and their messages: who may talk to the server, and in what order.

A message is refused (with a typed reason, counted per robot and reason) when its key names a
different robot than its body, when the robot is not on the configured allowlist, or when its
stamp does not advance past the last accepted one from that robot on that stream. Refusing is
never fatal: the message is dropped, everything accepted before stays.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


class Refused(ValueError):
    """A message the server will not use; ``reason`` is a short machine-readable tag."""

    def __init__(self, robot_id: str, reason: str, detail: str) -> None:
        self.robot_id = robot_id
        self.reason = reason
        super().__init__(f"{robot_id}: {reason}: {detail}")


@dataclass
class RobotRecord:
    robot_id: str
    alive: bool = False
    last_stamp_ns: dict[str, int] = field(default_factory=dict)
    accepted: Counter[str] = field(default_factory=Counter)
    refused: Counter[str] = field(default_factory=Counter)


class RobotRegistry:
    """Robots seen on the bus, their liveliness and per-stream stamp order."""

    def __init__(self, allowed: list[str] | None = None) -> None:
        self.allowed = set(allowed) if allowed else None
        self.robots: dict[str, RobotRecord] = {}
        self.refused_unknown: Counter[str] = Counter()

    def admit(self, key_robot_id: str | None, robot_id: str, stream: str, stamp_ns: int) -> None:
        """Accept a message or raise Refused. ``stream`` names the message kind (scan, tags...)."""
        if key_robot_id is not None and key_robot_id != robot_id:
            raise self._refuse(robot_id, "key-mismatch",
                               f"published under robot {key_robot_id!r}'s key")
        if self.allowed is not None and robot_id not in self.allowed:
            self.refused_unknown[robot_id] += 1
            raise self._refuse(robot_id, "unknown-robot", "not in the configured robot list")
        rec = self.robots.get(robot_id)
        if rec is None:
            rec = self.robots[robot_id] = RobotRecord(robot_id)
            log.info("robot %s joined", robot_id)
        last = rec.last_stamp_ns.get(stream)
        if last is not None and stamp_ns <= last:
            raise self._refuse(robot_id, "out-of-order",
                               f"{stream} stamp {stamp_ns} not after last accepted {last}")
        rec.last_stamp_ns[stream] = stamp_ns
        rec.accepted[stream] += 1

    def set_alive(self, robot_id: str, alive: bool) -> bool:
        """Record liveliness; returns True when it changed."""
        if self.allowed is not None and robot_id not in self.allowed:
            return False
        rec = self.robots.setdefault(robot_id, RobotRecord(robot_id))
        changed = rec.alive != alive
        rec.alive = alive
        return changed

    def _refuse(self, robot_id: str, reason: str, detail: str) -> Refused:
        rec = self.robots.get(robot_id)
        if rec is not None:
            rec.refused[reason] += 1
        err = Refused(robot_id, reason, detail)
        total = sum(r.refused[reason] for r in self.robots.values()) + (
            self.refused_unknown[robot_id] if reason == "unknown-robot" else 0)
        if total <= 10 or total % 1000 == 0:
            log.warning("refused message #%d: %s", total, err)
        return err

    def counters(self) -> dict[str, dict[str, int]]:
        out = {rid: {f"refused_{k}": v for k, v in r.refused.items()}
               | {f"accepted_{k}": v for k, v in r.accepted.items()}
               for rid, r in self.robots.items()}
        for rid, n in self.refused_unknown.items():
            out.setdefault(rid, {})["refused_unknown-robot"] = n
        return out
