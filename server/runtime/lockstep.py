"""A lockstep simulation's steps, taken whole: the same run every time.

In lockstep the simulator moves on only when every robot's agent has acknowledged the step,
and an agent acknowledges once the server's command for its scan is back. Within a step the
robots' messages reach the server in whatever order the network and the processes' timing
give, and the order matters (which scan sees which teammate's keyframes, where a sighting is
placed). So the server's worker takes a step at a time:

1. wait until every robot it expects has a scan queued (or ``step_barrier_s`` has passed);
   expected are the robots alive by their liveliness token or by the core, less those leaving
   and those that missed a step (a stranger with a token, a robot whose scans are refused:
   waited for once, then again only when a scan of theirs comes);
2. take the step's messages: robots coming and going (in robot order, each robot's in arrival
   order), the oldest scan of each robot at the step's stamp (in robot order), then the
   sightings of earlier steps (in robot order). A step's sightings wait for the next step:
   an agent may read a camera frame after it sent the step's scan, but it sends that frame's
   sightings before its next scan.

Queues are the node's ``Inbox``: name -> deque of items, control items by name in arrival
order.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

from server.runtime.inbox import Inbox
from server.runtime.work import TagsWork

ALIVE, TAGS = "#alive:", "#tags:"


class StepBarrier:
    """Which robots a step waits for, and the step's messages in a fixed order."""

    def __init__(self, barrier_s: float) -> None:
        self.barrier_s = barrier_s
        self.missed: set[str] = set()   # robots not waited for until they send a scan again
        self.timeouts = 0

    def take(self, inbox: Inbox, cv: threading.Condition, alive: set[str]
             ) -> list[tuple[str, Any]]:
        """The next step's messages; the caller holds ``cv`` (its ``wait`` releases it)."""
        queues = inbox.queues
        deadline = time.monotonic() + self.barrier_s
        while True:
            heads = _scan_heads(queues)
            waiting = (alive - _leaving(queues) - self.missed) - set(heads)
            if heads and not waiting:
                break
            left = deadline - time.monotonic()
            if left <= 0:
                if heads:
                    self.missed |= waiting
                    self.timeouts += 1
                break
            cv.wait(left)
        # robots coming and going in robot order (each robot's own in arrival order): the
        # order a fleet's tokens arrive in at the start differs from run to run, and the
        # order robots are added in gives them their graph symbols
        batch: list[tuple[str, Any]] = [(n, None) for n in sorted(
            n for n in inbox.control if n.startswith(ALIVE))]
        if heads:
            step = min(heads.values())
            batch += [(rid, None) for rid in sorted(heads) if heads[rid] == step]
            self.missed -= {rid for rid, _ in batch}
            batch += [(n, None) for n in sorted(n for n in queues if n.startswith(TAGS))
                      for _ in range(_count_before(queues[n], step))]
        else:  # nothing but sightings came: take them all
            batch += [(n, None) for n in sorted(n for n in queues if n.startswith(TAGS))
                      for _ in range(len(queues[n]))]
        return [(name, inbox.take_named(name)) for name, _ in batch]


def _scan_heads(queues: dict[str, deque[Any]]) -> dict[str, int]:
    """Robot -> stamp of its oldest queued scan."""
    return {name: q[0].scan.stamp_ns for name, q in queues.items()
            if q and not name.startswith("#")}


def _count_before(q: deque[TagsWork], stamp_ns: int) -> int:
    """How many items at the head of a sightings queue are older than ``stamp_ns``."""
    n = 0
    while n < len(q) and q[n].tags.stamp_ns < stamp_ns:
        n += 1
    return n


def _leaving(queues: dict[str, deque[Any]]) -> set[str]:
    """Robots whose latest queued liveliness change says they left."""
    return {name[len(ALIVE):] for name, q in queues.items()
            if name.startswith(ALIVE) and q and not q[-1].alive}
