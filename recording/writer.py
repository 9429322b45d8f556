"""Write bus messages into an MCAP file: the wire bytes unchanged, one channel per key.

Each message's log and publish time are its own ``stamp_ns``. A payload whose header does not
decode (or carries no stamp) is still written, at its receive time expressed on the messages'
clock (the last good stamp plus the receive time elapsed since it), and counted. The file is
flushed into a finished chunk every ``flush_period_s``, so a recorder that dies loses at most that
much; ``close()`` writes the summary that makes the file indexed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Literal

from mcap.writer import CompressionType, Writer

from recording.channels import MESSAGE_ENCODING, SCHEMA_ENCODING, header_of, kind_of
from schemas.errors import SchemaError

if TYPE_CHECKING:
    from recording.foxglove import FoxgloveView
    from recording.live import FoxgloveLive

log = logging.getLogger(__name__)

Compression = Literal["none", "zstd", "lz4"]
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}
PROFILE = "mrslam"


@dataclass
class RecorderStats:
    messages: Counter[str] = field(default_factory=Counter)   # per key
    payload_bytes: int = 0
    undecodable: Counter[str] = field(default_factory=Counter)  # header did not decode
    unstamped: int = 0
    unknown_keys: int = 0
    foxglove_messages: int = 0
    foxglove_errors: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"messages": sum(self.messages.values()), "keys": len(self.messages),
                "payload_bytes": self.payload_bytes,
                "undecodable": sum(self.undecodable.values()), "unstamped": self.unstamped,
                "unknown_keys": self.unknown_keys, "foxglove_messages": self.foxglove_messages,
                "foxglove_errors": self.foxglove_errors}


class McapRecorder:
    """Thread-safe: Zenoh calls ``add`` from several threads."""

    def __init__(self, path: str | Path, compression: Compression = "zstd",
                 foxglove_channels: bool = False, chunk_size: int = 1 << 20,
                 metadata: dict[str, str] | None = None,
                 live: FoxgloveLive | None = None) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO = self.path.open("wb")
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_COMPRESSION[compression])
        self._writer.start(profile=PROFILE, library="mrslam recorder")
        if metadata:
            self._writer.add_metadata("mrslam", metadata)
        self.foxglove = foxglove_channels
        self.live = live
        self._view: FoxgloveView | None = None
        if foxglove_channels or live is not None:
            from recording.foxglove import FoxgloveView

            self._view = FoxgloveView()
        self.stats = RecorderStats()
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._lock = threading.Lock()
        self._closed = False
        # the messages' clock against the receive clock, from the latest stamped message
        self._clock_ref: tuple[int, int] | None = None  # (stamp_ns, receive_ns)

    def add(self, key: str, payload: bytes, receive_ns: int | None = None) -> None:
        recv = time.time_ns() if receive_ns is None else receive_ns
        kind = kind_of(key)
        header = header_of(payload)
        with self._lock:
            if self._closed:
                return
            if header is not None and header[0] > 0:
                stamp, seq = header
                self._clock_ref = (stamp, recv)
            else:
                stamp, seq = self._receive_stamp(recv), 0
                if header is None:
                    self.stats.undecodable[key] += 1
                    n = sum(self.stats.undecodable.values())
                    if n <= 10 or n % 1000 == 0:
                        log.warning("undecodable payload #%d on %s (%d bytes), recorded at "
                                    "receive time", n, key, len(payload))
                else:
                    self.stats.unstamped += 1
            if kind.type_name is None:
                self.stats.unknown_keys += 1
            channel = self._channel(key, kind.schema_name, kind.schema_bytes(), MESSAGE_ENCODING)
            self._writer.add_message(channel, log_time=stamp, data=payload, publish_time=stamp,
                                     sequence=seq % 2**32)
            self.stats.messages[key] += 1
            self.stats.payload_bytes += len(payload)
            if self._view is not None and header is not None:
                self._add_foxglove(kind.type_name, payload, stamp)

    def _receive_stamp(self, receive_ns: int) -> int:
        if self._clock_ref is None:
            return 0  # before any stamped message: the start of the recording
        stamp, recv = self._clock_ref
        return max(0, stamp + receive_ns - recv)

    def _channel(self, topic: str, schema_name: str, schema: bytes, encoding: str,
                 schema_encoding: str = SCHEMA_ENCODING) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = 0
            if schema_name:
                sid = self._schemas.get(schema_name, 0)
                if not sid:
                    sid = self._schemas[schema_name] = self._writer.register_schema(
                        schema_name, schema_encoding, schema)
            ch = self._channels[topic] = self._writer.register_channel(topic, encoding, sid)
        return ch

    def _add_foxglove(self, type_name: str | None, payload: bytes, stamp_ns: int) -> None:
        """Called under the lock: the view's frame tree follows the messages in file order."""
        from recording.foxglove import MESSAGE_ENCODING, schema_of

        assert self._view is not None
        try:
            converted = self._view.convert(type_name, payload)
        except (SchemaError, ValueError) as e:
            self.stats.foxglove_errors += 1
            log.debug("no Foxglove view of a %s: %s", type_name, e)
            return
        if self.foxglove:
            for topic, msg in converted:
                schema = schema_of(msg)
                ch = self._channel(topic, schema.name, schema.data, MESSAGE_ENCODING,
                                   schema.encoding)
                self._writer.add_message(ch, log_time=stamp_ns, data=msg.encode(),
                                         publish_time=stamp_ns)
                self.stats.foxglove_messages += 1
        if self.live is not None:
            self.live.publish(converted, stamp_ns)

    def flush(self) -> None:
        """Close the chunk in progress and push it to the file (survives a crash after this)."""
        with self._lock:
            if not self._closed:
                self._writer.flush()

    def close(self) -> None:
        """Write the summary and close the file; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._writer.add_metadata("mrslam.recorder", {
                k: str(v) for k, v in self.stats.as_dict().items()})
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
