"""A ROS 1 bag (format 2.0) read record by record in file order, without its index.

For bags whose index cannot be read: written by an early or foreign writer (the scan_tools demo
bag's index data records give a length that disagrees with their entry count), cut short while
recording (no index at all) or truncated on copy. The format (wiki.ros.org/Bags/Format/2.0):

- the line ``#ROSBAG V2.0``, then records: a header (``<len>`` then fields ``<len>name=value``,
  little-endian lengths) and data (``<len>`` then bytes). The header's ``op`` field says what
  the record is: ``0x03`` bag header, ``0x05`` chunk, ``0x04`` index data, ``0x06`` chunk info,
  ``0x07`` connection, ``0x02`` message data;
- a chunk's data (``compression`` none, bz2 or lz4) holds connection and message-data records;
  a connection's data is a header of its own (``type``, ``message_definition``...), a message's
  header gives its connection (``conn``) and receive time (``time``).

Where a record cannot be parsed (a lying length, garbage), reading resumes at the next chunk
found after it; what lies after the last intact byte is counted as lost. Messages keep the
order they are written in.
"""

from __future__ import annotations

import bz2
import logging
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.offline.logs.records import BagError

log = logging.getLogger(__name__)

MAGIC = b"#ROSBAG V2.0\n"
OP_MSG_DATA, OP_BAG_HEADER, OP_INDEX_DATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = (
    0x02, 0x03, 0x04, 0x05, 0x06, 0x07)
KNOWN_OPS = {OP_MSG_DATA, OP_BAG_HEADER, OP_INDEX_DATA, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION}
MAX_HEADER = 1 << 20
U32 = struct.Struct("<I")


class RecordError(ValueError):
    """A record that cannot be parsed where it should start."""


@dataclass(frozen=True)
class Ros1Connection:
    id: int
    topic: str
    msgtype: str   # as rosbags names it: ``pkg/msg/Name``
    msgdef: str


@dataclass
class Ros1Records:
    """What one pass over the bag found: connections, and the messages of the wanted types in
    file order as (connection id, receive time [ns], raw bytes)."""

    connections: dict[int, Ros1Connection] = field(default_factory=dict)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    lost: list[str] = field(default_factory=list)   # what could not be read, and where


def _header(buf: bytes | memoryview, pos: int) -> tuple[dict[str, bytes], int]:
    """The record header at ``pos`` and the position after it."""
    if pos + 4 > len(buf):
        raise RecordError("cut inside a record's header length")
    (n,) = U32.unpack_from(buf, pos)
    if n > MAX_HEADER or pos + 4 + n > len(buf):
        raise RecordError(f"a header of {n} bytes runs past the end of the data")
    fields: dict[str, bytes] = {}
    i, end = pos + 4, pos + 4 + n
    while i < end:
        if i + 4 > end:
            raise RecordError("cut inside a header field")
        (k,) = U32.unpack_from(buf, i)
        i += 4
        if i + k > end:
            raise RecordError("header field longer than its header")
        name, sep, value = bytes(buf[i:i + k]).partition(b"=")
        if not sep:
            raise RecordError("header field without '='")
        fields[name.decode("ascii", "replace")] = value
        i += k
    if len(fields.get("op", b"")) != 1 or fields["op"][0] not in KNOWN_OPS:
        raise RecordError("no known op code")
    return fields, end


def _record(buf: bytes | memoryview, pos: int) -> tuple[dict[str, bytes], int, int]:
    """Header, start and length of the data of the record at ``pos`` (data may be cut)."""
    fields, p = _header(buf, pos)
    if p + 4 > len(buf):
        raise RecordError("cut before a record's data length")
    (n,) = U32.unpack_from(buf, p)
    return fields, p + 4, n


def _u32(fields: dict[str, bytes], name: str) -> int:
    try:
        return int(U32.unpack(fields[name])[0])
    except (KeyError, struct.error):
        raise RecordError(f"header field {name!r} missing or not 4 bytes") from None


def _decompress(kind: str, data: bytes | memoryview) -> bytes:
    """A chunk's records; as much of them as a cut stream gives."""
    if kind == "none":
        return bytes(data)
    if kind == "bz2":
        return bz2.BZ2Decompressor().decompress(data)
    if kind == "lz4":
        from lz4.frame import LZ4FrameDecompressor

        return bytes(LZ4FrameDecompressor().decompress(bytes(data)))
    raise RecordError(f"chunk compression {kind!r} is not known")


def _connection(fields: dict[str, bytes], data: bytes | memoryview) -> Ros1Connection:
    from rosbags.typesys.msg import normalize_msgtype

    conn = _u32(fields, "conn")
    inner = _plain_fields(data)
    topic = fields.get("topic", inner.get("topic", b"")).decode("utf-8", "replace")
    msgtype = inner.get("type", b"").decode("utf-8", "replace")
    return Ros1Connection(conn, topic, normalize_msgtype(msgtype) if msgtype else "",
                          inner.get("message_definition", b"").decode("utf-8", "replace"))


def _plain_fields(data: bytes | memoryview) -> dict[str, bytes]:
    """The fields of a connection record's data (a header without an op code)."""
    out: dict[str, bytes] = {}
    i = 0
    while i + 4 <= len(data):
        (k,) = U32.unpack_from(data, i)
        i += 4
        name, sep, value = bytes(data[i:i + k]).partition(b"=")
        if not sep:
            raise RecordError("connection field without '='")
        out[name.decode("ascii", "replace")] = value
        i += k
    return out


class _Pass:
    """One pass over the records, keeping messages whose type ``wanted`` accepts."""

    def __init__(self, wanted: Callable[[str], bool]) -> None:
        self.wanted = wanted
        self.out = Ros1Records()

    def connection(self, fields: dict[str, bytes], data: bytes | memoryview) -> None:
        c = _connection(fields, data)
        self.out.connections.setdefault(c.id, c)

    def message(self, fields: dict[str, bytes], data: bytes | memoryview) -> None:
        conn = _u32(fields, "conn")
        self.out.counts[conn] = self.out.counts.get(conn, 0) + 1
        c = self.out.connections.get(conn)
        if c is None or not self.wanted(c.msgtype):
            return
        raw = fields.get("time", b"")
        if len(raw) != 8:
            raise RecordError("message time is not 8 bytes")
        sec, nsec = struct.unpack("<II", raw)
        self.out.messages.append((conn, sec * 1_000_000_000 + nsec, bytes(data)))

    def chunk(self, body: bytes, cut: bool) -> None:
        pos = 0
        while pos < len(body):
            try:
                fields, start, n = _record(body, pos)
                if start + n > len(body):
                    raise RecordError("record longer than its chunk")
            except RecordError as e:
                if not cut:
                    self.out.lost.append(f"inside a chunk: {e}")
                return
            op = fields["op"][0]
            if op == OP_CONNECTION:
                self.connection(fields, body[start:start + n])
            elif op == OP_MSG_DATA:
                self.message(fields, body[start:start + n])
            pos = start + n


def _resync(buf: bytes | memoryview, pos: int) -> int | None:
    """The start of the next chunk record at or after ``pos`` that parses, or None."""
    data = bytes(buf)
    for m in re.finditer(rb"op=\x05", data[pos:]):
        hit = pos + m.start()
        for start in range(max(pos, hit - 256), hit - 4):
            try:
                fields, end = _header(buf, start)
            except RecordError:
                continue
            if start < hit < end and fields["op"][0] == OP_CHUNK:
                return start
    return None


def read_records(path: Path, wanted: Callable[[str], bool]) -> Ros1Records:
    """Every connection of the bag, and the messages whose type ``wanted`` accepts, in file
    order. Raises ``BagError`` if the file is not a ROS 1 bag of format 2.0."""
    buf = path.read_bytes()
    if not buf:
        raise BagError(f"{path}: empty file, not a ROS bag")
    if not buf.startswith(MAGIC):
        first = buf[:13].split(b"\n")[0]
        if first.startswith(b"#ROSBAG V"):
            raise BagError(f"{path}: ROS bag format {first[9:].decode('ascii', 'replace')} "
                           f"is not supported (2.0 is)")
        raise BagError(f"{path}: not a ROS bag")
    view = memoryview(buf)
    run = _Pass(wanted)
    pos = len(MAGIC)
    while pos < len(buf):
        try:
            fields, start, n = _record(view, pos)
        except RecordError as e:
            nxt = _resync(view, pos + 1)
            if nxt is None:
                run.out.lost.append(f"from byte {pos} of {len(buf)}: {e}")
                break
            run.out.lost.append(f"bytes {pos}-{nxt}: {e}")
            pos = nxt
            continue
        op = fields["op"][0]
        cut = start + n > len(buf)
        data = view[start:min(start + n, len(buf))]
        if op == OP_CHUNK:
            try:
                run.chunk(_decompress(fields.get("compression", b"none").decode(), data), cut)
            except (RecordError, OSError, EOFError, RuntimeError, ValueError) as e:
                run.out.lost.append(f"chunk at byte {pos}: {e}")
        elif op == OP_CONNECTION and not cut:
            run.connection(fields, data)
        elif op == OP_INDEX_DATA and not cut:
            # the entries are 12 bytes each (time, offset); some writers give another length
            try:
                _record(view, start + n)
            except RecordError:
                n = 12 * _u32(fields, "count")
        if cut:
            run.out.lost.append(f"the file ends at byte {len(buf)}, inside a record that "
                                f"starts at byte {pos} (its intact part is read)")
            break
        pos = start + n
    return run.out


def deserializer(records: Ros1Records) -> Callable[[bytes, str], Any]:
    """A function decoding a message of ``records`` by its type, from the bag's own message
    definitions (rosbags' ROS 1 deserialiser)."""
    from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    # a definition the bag refers to but does not carry (old bags name ``roslib/Header`` where
    # their messages say ``Header``) is taken from ROS 1's last release
    types: dict[str, Any] = dict(get_typestore(Stores.ROS1_NOETIC).fielddefs)
    for c in records.connections.values():
        if c.msgtype and c.msgdef:
            try:
                types.update(get_types_from_msg(c.msgdef, c.msgtype))
            except TypesysError as e:   # its messages will not decode, and are counted
                log.warning("%s: the message definition of %s cannot be read (%s)", c.topic,
                            c.msgtype, e)
    store.register(types)
    return store.deserialize_ros1
