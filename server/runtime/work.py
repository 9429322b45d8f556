"""What the server's worker does, one typed item at a time (``server.runtime.node``).

Zenoh's threads and the console put these into the worker's inbox (``server.runtime.inbox``); the
worker hands each to its handler by type. Scans carry the robot's own stamp beside the one
mapped into the server's time: the command goes back with the robot's own.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from schemas import Scan, TagDetections
from server.command.operator import OperatorCommand
from server.runtime.cluster import Handover


@dataclass(frozen=True)
class ScanWork:
    scan: Scan                  # its stamp in the server's time
    own_stamp_ns: int           # the robot's own stamp of it


@dataclass(frozen=True)
class TagsWork:
    tags: TagDetections         # its stamp in the server's time


@dataclass(frozen=True)
class AliveWork:
    robot_id: str
    alive: bool


@dataclass(frozen=True)
class GiveWork:
    """Another worker asks for the team of the first of ``robots`` served here."""

    query: Any
    robots: list[str]


@dataclass(frozen=True)
class AdoptWork:
    """A team asked for has come (or not) from another worker."""

    handover: Handover


@dataclass(frozen=True)
class OrderWork:
    """An operator's order, and the answer its asker waits on."""

    command: OperatorCommand
    answer: Future[tuple[int, str]]


Work = ScanWork | TagsWork | AliveWork | GiveWork | AdoptWork | OrderWork


def robot_of(item: Work) -> str:
    """The robot an item is about, for the log ("" when none)."""
    if isinstance(item, ScanWork):
        return item.scan.robot_id
    if isinstance(item, TagsWork):
        return item.tags.robot_id
    if isinstance(item, AliveWork):
        return item.robot_id
    return ""
