"""Read a recording back, including damaged ones.

The scan walks the file record by record (MCAP: opcode u8, length u64, body) and trusts a chunk
only when its CRC matches. What cannot be trusted is skipped and counted: a chunk whose data is
damaged or cut off, messages on channels whose definition was lost, bytes between two records
where the framing broke. After broken framing the scan resumes at the next chunk, found from the
summary's chunk index when the file has an intact one, else by searching for a record that is a
self-consistent chunk. When nothing at all can be read, ``RecordingError`` says why.
"""

from __future__ import annotations

import logging
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from recording.channels import type_name_of_schema

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06
OP_CHUNK_INDEX, OP_STATISTICS, OP_DATA_END = 0x08, 0x0B, 0x0F
KNOWN_OPS = frozenset(range(0x01, 0x10))
FOOTER_LEN = 1 + 8 + 20
COMPRESSIONS = ("", "zstd", "lz4")


class RecordingError(ValueError):
    """A recording that cannot be read at all (missing, empty, not MCAP, nothing readable)."""

    user_error = True


class _Bad(ValueError):
    """A record whose bytes do not parse."""


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    type_name: str | None  # mrslam message type from the channel's schema; None: unknown
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes


@dataclass
class ReadReport:
    """What was recovered and what was not."""

    messages: int = 0
    expected_messages: int | None = None  # from the summary's statistics, when intact
    counted_lost: int = 0  # messages seen in damaged chunks or on unknown channels
    damaged_chunks: int = 0
    skipped_bytes: int = 0
    finished: bool = False  # the file ends with a valid footer
    problems: list[str] = field(default_factory=list)

    @property
    def unreadable_messages(self) -> int:
        """Messages known to be in the file but not recovered (a lower bound without a summary)."""
        if self.expected_messages is not None:
            return max(self.expected_messages - self.messages, self.counted_lost)
        return self.counted_lost

    @property
    def intact(self) -> bool:
        return self.finished and not self.problems


@dataclass
class Recording:
    path: Path
    messages: list[RecordedMessage]
    report: ReadReport

    def in_time_order(self) -> list[RecordedMessage]:
        """By log time; messages with equal times keep the order they were written in."""
        return sorted(self.messages, key=lambda m: m.log_time_ns)


class _Cursor:
    def __init__(self, buf: bytes | memoryview) -> None:
        self.buf, self.pos = memoryview(buf), 0

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.buf):
            raise _Bad(f"field of {n} bytes runs past the record's end")
        out = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return out

    def u16(self) -> int:
        return int(struct.unpack("<H", self.take(2))[0])

    def u32(self) -> int:
        return int(struct.unpack("<I", self.take(4))[0])

    def u64(self) -> int:
        return int(struct.unpack("<Q", self.take(8))[0])

    def text(self) -> str:
        try:
            return self.take(self.u32()).decode()
        except UnicodeDecodeError as e:
            raise _Bad(f"string is not UTF-8 ({e})") from None

    def rest(self) -> bytes:
        return self.take(len(self.buf) - self.pos)


def _records(buf: bytes | memoryview) -> list[tuple[int, memoryview]]:
    """Split a byte run into (opcode, body) records; raises _Bad at the first broken frame."""
    out, view, pos = [], memoryview(buf), 0
    while pos < len(view):
        if pos + 9 > len(view):
            raise _Bad("record header cut off")
        op, length = view[pos], int(struct.unpack_from("<Q", view, pos + 1)[0])
        if op not in KNOWN_OPS or pos + 9 + length > len(view):
            raise _Bad(f"broken record frame at byte {pos}")
        out.append((op, view[pos + 9:pos + 9 + length]))
        pos += 9 + length
    return out


class _Scanner:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.report = ReadReport()
        self.schemas: dict[int, str] = {}
        self.channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
        self.messages: list[RecordedMessage] = []
        self.chunk_offsets: list[int] = []
        self.data_limit = len(data)

    # -- summary (at the end of a finished file) --------------------------------------------
    def read_summary(self) -> None:
        d, footer_at = self.data, len(self.data) - len(MAGIC) - FOOTER_LEN
        if footer_at < len(MAGIC) or d[-len(MAGIC):] != MAGIC or d[footer_at] != OP_FOOTER:
            self.report.problems.append("no footer (the file was cut off or not finished)")
            return
        c = _Cursor(d[footer_at + 9:footer_at + FOOTER_LEN])
        summary_start, _offsets_start, crc = c.u64(), c.u64(), c.u32()
        if not len(MAGIC) <= summary_start <= footer_at:
            if summary_start:
                self.report.problems.append("footer points outside the file")
            self.report.finished = summary_start == 0
            self.data_limit = footer_at
            return
        if crc and zlib.crc32(d[summary_start:footer_at + 9 + 16]) != crc:
            self.report.problems.append("summary section fails its CRC; not used")
            return
        try:
            records = _records(memoryview(d)[summary_start:footer_at])
            for op, body in records:
                self._summary_record(op, body)
        except _Bad as e:
            self.report.problems.append(f"summary section unreadable ({e}); not used")
            self.schemas.clear()
            self.channels.clear()
            self.chunk_offsets.clear()
            self.report.expected_messages = None
            return
        self.report.finished = True
        self.data_limit = summary_start

    def _summary_record(self, op: int, body: memoryview) -> None:
        c = _Cursor(body)
        if op in (OP_SCHEMA, OP_CHANNEL):
            self._definition(op, body)
        elif op == OP_CHUNK_INDEX:
            c.take(16)  # message start and end times
            self.chunk_offsets.append(c.u64())
        elif op == OP_STATISTICS:
            self.report.expected_messages = c.u64()

    def _definition(self, op: int, body: memoryview) -> None:
        c = _Cursor(body)
        if op == OP_SCHEMA:
            sid, name = c.u16(), c.text()
            self.schemas[sid] = name
        else:
            cid, sid, topic = c.u16(), c.u16(), c.text()
            self.channels[cid] = (topic, sid)

    # -- data section -------------------------------------------------------------------------
    def scan(self) -> None:
        d, pos, limit = self.data, len(MAGIC), self.data_limit
        while pos < limit:
            if pos + 9 > limit:
                self._skip(pos, limit, "the file ends inside a record header")
                break
            op, length = d[pos], int(struct.unpack_from("<Q", d, pos + 1)[0])
            end = pos + 9 + length
            if op not in KNOWN_OPS or end > limit:
                if op == OP_CHUNK and end > limit:
                    self._cut_chunk(memoryview(d)[pos + 9:limit])
                nxt = self._resync(pos + 1, limit)
                self._skip(pos, nxt, f"broken record at byte {pos}")
                pos = nxt
                continue
            body = memoryview(d)[pos + 9:end]
            if op == OP_DATA_END:
                break
            try:
                if op == OP_CHUNK:
                    self._chunk(body)
                elif op in (OP_SCHEMA, OP_CHANNEL):
                    self._definition(op, body)
                elif op == OP_MESSAGE:
                    self._message(body)
            except _Bad as e:
                self.report.problems.append(f"record at byte {pos}: {e}")
                if not self._plausible_record(end, limit):
                    nxt = self._resync(pos + 1, limit)
                    self._skip(pos, nxt, f"damaged record at byte {pos}")
                    pos = nxt
                    continue
            pos = end

    def _skip(self, start: int, end: int, why: str) -> None:
        if end > start:
            self.report.skipped_bytes += end - start
            self.report.problems.append(f"{why}: skipped {end - start} bytes")

    def _plausible_record(self, pos: int, limit: int) -> bool:
        if pos == limit:
            return True
        if pos + 9 > limit or self.data[pos] not in KNOWN_OPS:
            return False
        return pos + 9 + int(struct.unpack_from("<Q", self.data, pos + 1)[0]) <= limit

    def _resync(self, start: int, limit: int) -> int:
        """The next offset where a chunk starts: from the summary's index, else by search."""
        for off in sorted(self.chunk_offsets):
            if start <= off < limit and self._is_chunk_frame(off, limit):
                return off
        pos = start
        while (pos := self.data.find(bytes([OP_CHUNK]), pos, limit)) != -1:
            if self._is_chunk_frame(pos, limit):
                return pos
            pos += 1
        return limit

    def _is_chunk_frame(self, pos: int, limit: int) -> bool:
        """A chunk record whose inner lengths add up exactly (false positives are unlikely)."""
        d = self.data
        if pos + 9 + 36 > limit or d[pos] != OP_CHUNK:
            return False
        length = int(struct.unpack_from("<Q", d, pos + 1)[0])
        if pos + 9 + length > limit:
            return False
        n_comp = int(struct.unpack_from("<I", d, pos + 9 + 28)[0])
        if n_comp > 8 or pos + 9 + 32 + n_comp + 8 > limit:
            return False
        comp = d[pos + 9 + 32:pos + 9 + 32 + n_comp]
        n_rec = int(struct.unpack_from("<Q", d, pos + 9 + 32 + n_comp)[0])
        return comp.decode(errors="replace") in COMPRESSIONS and 32 + n_comp + 8 + n_rec == length

    # -- chunks and messages ------------------------------------------------------------------
    def _chunk(self, body: memoryview) -> None:
        c = _Cursor(body)
        c.take(16)  # message start and end times
        size, crc, comp = c.u64(), c.u32(), c.text()
        payload = c.take(c.u64())
        try:
            raw = _decompress(comp, payload, size)
        except _Bad as e:
            self.report.damaged_chunks += 1
            raise _Bad(f"chunk data damaged ({e})") from None
        if len(raw) != size or (crc and zlib.crc32(raw) != crc):
            self.report.damaged_chunks += 1
            self.report.counted_lost += _count_messages(raw)
            raise _Bad("chunk fails its CRC; its messages are not used")
        for op, rec in _records(raw):
            if op in (OP_SCHEMA, OP_CHANNEL):
                self._definition(op, rec)
            elif op == OP_MESSAGE:
                self._message(rec)

    def _cut_chunk(self, partial: memoryview) -> None:
        """A chunk the file ends inside: count the messages that its prefix shows."""
        self.report.damaged_chunks += 1
        try:
            c = _Cursor(partial)
            c.take(28)  # times, uncompressed size and CRC
            comp = c.text()
            c.take(8)
            raw = _decompress(comp, c.rest(), None)
        except _Bad:
            return
        self.report.counted_lost += _count_messages(raw)

    def _message(self, body: memoryview) -> None:
        c = _Cursor(body)
        cid, seq, log_ns, pub_ns = c.u16(), c.u32(), c.u64(), c.u64()
        channel = self.channels.get(cid)
        if channel is None:
            self.report.counted_lost += 1
            if self.report.counted_lost <= 1:
                self.report.problems.append(f"messages on channel {cid}, whose definition "
                                            "was lost")
            return
        topic, sid = channel
        type_name = type_name_of_schema(self.schemas.get(sid, ""))
        self.messages.append(RecordedMessage(topic, type_name, log_ns, pub_ns, seq, c.rest()))


def _decompress(comp: str, data: bytes, size: int | None) -> bytes:
    """Decompress a chunk's records; with ``size`` None, as much as a cut-off stream gives."""
    try:
        if comp == "":
            return data
        if comp == "zstd":
            import zstandard

            return bytes(zstandard.ZstdDecompressor().decompressobj().decompress(data))
        if comp == "lz4":
            import lz4.frame

            if size is None:
                return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
            return bytes(lz4.frame.decompress(data))
    except Exception as e:  # each library raises its own error type for bad input
        raise _Bad(f"{comp} data does not decompress: {type(e).__name__}") from None
    raise _Bad(f"unknown compression {comp!r}")


def _count_messages(raw: bytes) -> int:
    """Message records in a (possibly damaged or cut) run of records, up to the first break."""
    n, view, pos = 0, memoryview(raw), 0
    while pos + 9 <= len(view):
        op, length = view[pos], int(struct.unpack_from("<Q", view, pos + 1)[0])
        if op not in KNOWN_OPS or pos + 9 + length > len(view):
            break
        n += op == OP_MESSAGE
        pos += 9 + length
    return n


def read_recording(path: str | Path) -> Recording:
    """Every readable message of the recording at ``path``, with a report of what was not."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise RecordingError(f"{p}: cannot read ({e.strerror})") from None
    if not data:
        raise RecordingError(f"{p}: empty file, not a recording")
    if not data.startswith(MAGIC):
        raise RecordingError(f"{p}: not an MCAP file (it does not start with the MCAP magic)")
    scanner = _Scanner(data)
    scanner.read_summary()
    scanner.scan()
    report = scanner.report
    report.messages = len(scanner.messages)
    if not scanner.messages and (report.problems or report.counted_lost):
        raise RecordingError(f"{p}: no readable message ({'; '.join(report.problems[:3])})")
    if report.problems:
        log.warning("%s: recovered %d messages, %d unreadable; %s", p, report.messages,
                    report.unreadable_messages, "; ".join(report.problems[:5]))
    return Recording(p, scanner.messages, report)
