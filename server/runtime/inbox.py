"""The server worker's queues: what it does next, and how robots take turns.

Zenoh's threads put admitted messages here; the worker takes one item at a time:

1. control items first (a robot's liveliness changing, a team moving between workers), in the
   order they came;
2. then the robots' messages, one robot at a time in turn (round robin): a robot with many
   messages waiting, or a thousand robots, do not take another robot's share;
3. robots the server trusts (they hold a liveliness token, or the configuration names them)
   are served before newcomers admitted by probation alone, so a flood of new ids cannot
   starve a fleet's own robots.

Each robot's queue holds at most ``per_robot`` messages: when the server is behind, the oldest
waiting message of that robot goes (counted in ``dropped``).

Queue names are the node's: a robot id for its scans, ``#tags:<id>`` for its sightings,
``#alive:<id>``, ``#give:`` and ``#adopt:`` for control items.
"""

from __future__ import annotations

from collections import deque
from typing import Any

#: the two turns: robots the server trusts, then newcomers
TRUSTED, NEWCOMER = 0, 1


class Inbox:
    def __init__(self, per_robot: int) -> None:
        self.per_robot = per_robot
        self.queues: dict[str, deque[Any]] = {}
        #: names of waiting control items, one per item, in arrival order
        self.control: deque[str] = deque()
        self._turns: tuple[deque[str], deque[str]] = (deque(), deque())
        self._in_turn: set[str] = set()
        self.dropped: dict[str, int] = {}
        self._count = 0     # items waiting

    def __len__(self) -> int:
        return self._count

    def put(self, name: str, item: Any, tier: int = TRUSTED) -> None:
        """A robot's message; the robot joins the turn of ``tier`` if it is not in one."""
        q = self.queues.setdefault(name, deque())
        if len(q) >= self.per_robot:
            q.popleft()   # the server is behind: the oldest waiting message goes
            self.dropped[name] = self.dropped.get(name, 0) + 1
        else:
            self._count += 1
        q.append(item)
        if name not in self._in_turn:
            self._in_turn.add(name)
            self._turns[tier].append(name)

    def put_control(self, name: str, item: Any) -> None:
        self.queues.setdefault(name, deque()).append(item)
        self.control.append(name)
        self._count += 1

    def take(self) -> tuple[str, Any] | None:
        """The next item: a control item, else the next robot's oldest message in turn."""
        if self.control:
            name = self.control.popleft()
            return name, self._pop(name)
        for turn in self._turns:
            while turn:
                name = turn.popleft()
                q = self.queues.get(name)
                if not q:     # emptied meanwhile (a lockstep step took it)
                    self._in_turn.discard(name)
                    continue
                item = q.popleft()
                self._count -= 1
                if q:
                    turn.append(name)
                else:
                    self._in_turn.discard(name)
                    del self.queues[name]
                return name, item
        return None

    def take_named(self, name: str) -> Any:
        """The oldest item of one queue (a lockstep step takes its messages by name)."""
        if name in self.control:
            self.control.remove(name)     # the first occurrence is the item at the head
        return self._pop(name)

    def _pop(self, name: str) -> Any:
        q = self.queues[name]
        item = q.popleft()
        self._count -= 1
        if not q:
            del self.queues[name]   # ids come and go: no empty queue stays behind
        return item
