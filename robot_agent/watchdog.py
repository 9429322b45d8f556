"""Stop the robot when its commands run out or the server goes away.

A command is valid for its ``ttl_s`` from the moment it arrives, measured on the robot's
monotonic clock (simulation time in simulation), so unsynchronised clocks between server and
robot do not matter, and neither does the robot's own clock stepping: on a clock that stepped
back an hour a deadline would lie an hour ahead. ``expired`` reports once per lapse, so the
caller stops the base once.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Watchdog:
    deadline_ns: int | None = None
    timeouts: int = 0
    server_losses: int = 0

    def feed(self, now_ns: int, ttl_s: float) -> None:
        """A command arrived at ``now_ns``; it holds for ``ttl_s``."""
        self.deadline_ns = now_ns + round(ttl_s * 1e9)

    def expired(self, now_ns: int) -> bool:
        """True once when the last command's time has run out."""
        if self.deadline_ns is not None and now_ns > self.deadline_ns:
            self.deadline_ns = None
            self.timeouts += 1
            return True
        return False

    def server_lost(self) -> None:
        """The server's liveliness vanished: forget the command, so the robot stays stopped."""
        self.deadline_ns = None
        self.server_losses += 1
