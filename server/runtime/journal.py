"""The server's journal: everything it accepted, in the order it processed it.

The worker appends each scan, tag-sighting message and liveliness change before the core
sees it (write-ahead), with the time the core ran its periodic work on. The core is
deterministic given that sequence, so replaying the journal into a fresh core gives back the
same robots, graphs, teams and merges: a server killed at any moment resumes where it was.

Files: ``<state_dir>/journal-NNNN.mcap``, one segment per server start (an MCAP file cannot be
appended to once finished, and a killed server never finishes its file). Each record is a
msgpack envelope on the channel ``journal``: ``{"k": "scan" | "tags" | "alive", "now": int |
None, "msg": bytes, "rid": str, "alive": bool}``, an operator's order (``{"k": "operator",
"now": int, "cmd": {...}}``, ``server.command.operator``), or, for a server split over workers,
a team that left (``{"k": "gave", "rids": [str]}``) or came (``{"k": "adopted", "parcel":
bytes}``); the MCAP sequence number is the processing order across all segments. Chunks are
closed at least once a second, so a crash loses at most that much; a segment cut anywhere (a
torn tail) is read up to its last intact chunk.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import msgspec

from schemas import Scan, TagDetections
from schemas.codec import decode, encode
from schemas.errors import SchemaError
from server.command.operator import OperatorCommand
from server.command.operator import parse as parse_order
from server.runtime import handover

if TYPE_CHECKING:
    from server.core import ServerCore

log = logging.getLogger(__name__)

TOPIC = "journal"
SEGMENT_GLOB = "journal-*.mcap"


class JournalError(ValueError):
    """A state folder that cannot hold a journal (not a folder, not writable)."""

    user_error = True   # the CLI says it in one line (exit code 2)


@dataclass(frozen=True)
class Entry:
    """One thing the server processed."""

    kind: str                       # scan | tags | alive | gave | adopted | operator
    now_ns: int | None              # the time the core's periodic work ran on (scans)
    message: Scan | TagDetections | None = None
    sequence: int = 0               # processing order across all segments
    robot_id: str = ""              # alive
    alive: bool = False
    robot_ids: list[str] = field(default_factory=list)   # gave: the team that left
    parcel: bytes = b""             # adopted: the team that came (server.runtime.handover)
    order: OperatorCommand | None = None   # operator: the order (its stamp in now_ns)


@dataclass
class ReplayReport:
    segments: int = 0
    entries: int = 0                     # read (replayed or already in the snapshot)
    from_sequence: int = 0
    skipped: int = 0                     # already in the snapshot
    last_sequence: int = -1
    unreadable: int = 0                  # records that did not decode
    problems: list[str] = field(default_factory=list)   # torn tails, damaged chunks
    seconds: float = 0.0


class JournalWriter:
    """Appends to a new segment of ``state_dir``'s journal (one thread)."""

    def __init__(self, state_dir: str | Path, flush_period_s: float = 1.0,
                 first_sequence: int = 0) -> None:
        from mcap.writer import CompressionType, Writer

        self.dir = Path(state_dir)
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise JournalError(f"state folder {self.dir}: {e.strerror or e}") from e
        n = 1 + max((_segment_number(p) for p in self.dir.glob(SEGMENT_GLOB)), default=0)
        self.path = self.dir / f"journal-{n:04d}.mcap"
        self._file: BinaryIO = self.path.open("wb")
        self._writer = Writer(self._file, chunk_size=256 << 10,
                              compression=CompressionType.ZSTD)
        self._writer.start(profile="mrslam-journal", library="mrslam server")
        self._channel = self._writer.register_channel(TOPIC, "msgpack", 0)
        self.sequence = first_sequence
        self.flush_period_s = flush_period_s
        self.next_flush = time.monotonic() + flush_period_s
        self.bytes = 0
        self.seconds = 0.0          # spent journalling (the worker's time)
        self._closed = False

    def scan(self, msg: Scan, now_ns: int | None) -> None:
        self._add({"k": "scan", "now": now_ns, "msg": encode(msg)}, msg.stamp_ns)

    def tags(self, msg: TagDetections) -> None:
        self._add({"k": "tags", "now": None, "msg": encode(msg)}, msg.stamp_ns)

    def alive(self, robot_id: str, alive: bool, stamp_ns: int) -> None:
        self._add({"k": "alive", "now": None, "rid": robot_id, "alive": alive}, stamp_ns)

    def operator(self, cmd: OperatorCommand, stamp_ns: int) -> None:
        """An operator's order (``server.command.operator``), before the core carries it out."""
        self._add({"k": "operator", "now": stamp_ns, "cmd": cmd.as_dict()}, stamp_ns)

    def gave(self, robot_ids: list[str], stamp_ns: int) -> None:
        """These robots' team went to another worker (``server.runtime.cluster``)."""
        self._add({"k": "gave", "now": None, "rids": list(robot_ids)}, stamp_ns)

    def adopted(self, parcel: bytes, stamp_ns: int) -> None:
        """A team came from another worker: its parcel (``server.runtime.handover``) whole."""
        self._add({"k": "adopted", "now": None, "parcel": parcel}, stamp_ns)

    def _add(self, envelope: dict[str, Any], stamp_ns: int) -> None:
        if self._closed:
            return
        t0 = time.perf_counter()
        data = msgspec.msgpack.encode(envelope)
        self._writer.add_message(self._channel, log_time=max(stamp_ns, 0), data=data,
                                 publish_time=max(stamp_ns, 0),
                                 sequence=self.sequence % 2**32)
        self.sequence += 1
        self.bytes += len(data)
        if time.monotonic() >= self.next_flush:
            self.flush()
        self.seconds += time.perf_counter() - t0

    def flush(self, sync: bool = True) -> None:
        """Close the chunk in progress and hand it to the operating system — what a killed
        process keeps — and (``sync``) to the disk: what a power cut keeps. Without ``sync``
        the caller calls ``sync`` soon, e.g. from another thread."""
        if self._closed:
            return
        self._writer.flush()
        self._file.flush()
        if sync:
            self.sync()
        self.next_flush = time.monotonic() + self.flush_period_s

    def sync(self) -> None:
        """Wait until what was flushed is on the disk (safe beside further writes)."""
        if not self._closed:
            os.fsync(self._file.fileno())

    def close(self) -> None:
        if self._closed:
            return
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        self._closed = True


def _segment_number(path: Path) -> int:
    try:
        return int(path.stem.split("-", 1)[1])
    except (IndexError, ValueError):
        return 0


def read_journal(state_dir: str | Path, report: ReplayReport | None = None
                 ) -> Iterator[Entry]:
    """Every readable entry of every segment, in processing order."""
    from recording.reader import RecordingError, read_recording

    report = report if report is not None else ReplayReport()
    segments = sorted(Path(state_dir).glob(SEGMENT_GLOB), key=_segment_number)
    for path in segments:
        report.segments += 1
        try:
            rec = read_recording(path)
        except (RecordingError, OSError) as e:
            report.problems.append(f"{path.name}: {e}")
            continue
        report.problems += [f"{path.name}: {p}" for p in rec.report.problems]
        for m in rec.messages:
            if m.topic != TOPIC:
                continue
            try:
                entry = _entry(msgspec.msgpack.decode(m.data), m.sequence)
            except (msgspec.DecodeError, SchemaError, KeyError, TypeError, ValueError) as e:
                report.unreadable += 1
                log.warning("journal %s: a record does not decode (%s); skipped", path.name, e)
                continue
            report.entries += 1
            yield entry


def _entry(env: dict[str, Any], sequence: int) -> Entry:
    kind = env["k"]
    if kind == "scan":
        return Entry("scan", env["now"], decode(env["msg"], Scan), sequence=sequence)
    if kind == "tags":
        return Entry("tags", None, decode(env["msg"], TagDetections), sequence=sequence)
    if kind == "alive":
        return Entry("alive", None, robot_id=str(env["rid"]), alive=bool(env["alive"]),
                     sequence=sequence)
    if kind == "gave":
        return Entry("gave", None, robot_ids=[str(r) for r in env["rids"]], sequence=sequence)
    if kind == "adopted":
        return Entry("adopted", None, parcel=bytes(env["parcel"]), sequence=sequence)
    if kind == "operator":
        return Entry("operator", int(env["now"]), order=parse_order(env["cmd"]),
                     sequence=sequence)
    raise ValueError(f"unknown journal record kind {kind!r}")


def replay(core: ServerCore, state_dir: str | Path, from_sequence: int = 0) -> ReplayReport:
    """Feed ``core`` what the journal holds from entry ``from_sequence`` on (the entries
    before are in the snapshot it came from), in the order the live server did. No commands
    are planned (they went out before, and the robots have moved on since): the navigators
    go on from where the snapshot left them and plan afresh at the next live scan. The events
    it raises again were published before and are dropped."""
    report = ReplayReport(from_sequence=from_sequence)
    t0 = time.monotonic()
    navigate, core.navigate = core.navigate, False   # commands are not sent again: no need
    try:                                            # to plan them (the robots moved on)
        _feed(core, read_journal(state_dir, report), from_sequence, report)
    finally:
        core.navigate = navigate
    core.pop_events()
    report.seconds = time.monotonic() - t0
    return report


def _feed(core: ServerCore, entries: Iterator[Entry], from_sequence: int,
          report: ReplayReport) -> None:
    for e in entries:
        report.last_sequence = e.sequence
        if e.sequence < from_sequence:
            report.skipped += 1
            continue
        try:
            if e.kind == "scan":
                assert isinstance(e.message, Scan)
                core.on_scan(e.message, e.now_ns)
            elif e.kind == "tags":
                assert isinstance(e.message, TagDetections)
                core.on_tags(e.message)
            elif e.kind == "gave":
                for rid in e.robot_ids:
                    handover.release(core, rid)
            elif e.kind == "adopted":
                handover.adopt(core, handover.unpack(e.parcel))
            elif e.kind == "operator":
                assert e.order is not None and e.now_ns is not None
                core.operate(e.order, e.now_ns)
            else:
                core.set_alive(e.robot_id, e.alive)
        except Exception as exc:   # as live: one message's failure does not stop the rest
            report.unreadable += 1
            log.warning("journal replay: a %s failed again: %s", e.kind, exc)
