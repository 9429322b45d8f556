"""ROS 2 storage files read without the bag's ``metadata.yaml``.

A recording killed before it closed leaves its ``.mcap`` without a summary or its folder without
``metadata.yaml``, and a bag is often handed over as its one ``.mcap`` or ``.db3`` file. Such a
file is read here on its own, in file order:

- MCAP: record by record (the mcap library's non-seeking reader), until the data ends or stops
  making sense; messages are decoded (CDR) by the types the file's own schemas define, others
  by ROS 2 Jazzy's;
- SQLite (``.db3``): the ``topics`` and ``messages`` tables, decoded by the definitions in its
  ``message_definitions`` table where it has one, else by ROS 2 Jazzy's.
"""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.offline.logs.records import BagError

log = logging.getLogger(__name__)


@dataclass
class Ros2Records:
    """Topics (topic → type), message counts, the wanted messages in file order as (topic,
    type, receive time [ns], raw CDR bytes), a decoder, and what could not be read."""

    topics: dict[str, str] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    messages: list[tuple[str, str, int, bytes]] = field(default_factory=list)
    definitions: dict[str, tuple[str, str]] = field(default_factory=dict)  # type -> (fmt, text)
    lost: list[str] = field(default_factory=list)

    def decoder(self) -> Callable[[bytes, str], Any]:
        from rosbags.typesys import (
            Stores,
            TypesysError,
            get_types_from_idl,
            get_types_from_msg,
            get_typestore,
        )

        types: dict[str, Any] = dict(get_typestore(Stores.ROS2_JAZZY).fielddefs)
        for name, (fmt, text) in self.definitions.items():
            try:
                types.update(get_types_from_idl(text) if fmt == "ros2idl"
                             else get_types_from_msg(text, name))
            except TypesysError as e:
                log.warning("the definition of %s cannot be read (%s): ROS 2 Jazzy's is used",
                            name, e)
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        return store.deserialize_cdr


def read_mcap(path: Path, wanted: Callable[[str], bool]) -> Ros2Records:
    """The messages of an MCAP file in file order, as far as it can be read."""
    from mcap.reader import NonSeekingReader

    out = Ros2Records()
    with path.open("rb") as f:
        try:
            for schema, channel, message in NonSeekingReader(f).iter_messages(
                    log_time_order=False):
                ty = schema.name if schema is not None else ""
                out.topics.setdefault(channel.topic, ty)
                out.counts[channel.topic] = out.counts.get(channel.topic, 0) + 1
                if schema is not None and ty not in out.definitions and schema.data:
                    out.definitions[ty] = (schema.encoding, schema.data.decode("utf-8",
                                                                               "replace"))
                if wanted(ty) and channel.message_encoding == "cdr":
                    out.messages.append((channel.topic, ty, int(message.log_time),
                                         bytes(message.data)))
        except Exception as e:   # the mcap library fails on damaged data in many ways
            out.lost.append(f"reading stopped at byte {f.tell()} of {path.stat().st_size}: "
                            f"{type(e).__name__}: {e}")
    return out


def read_db3(path: Path, wanted: Callable[[str], bool]) -> Ros2Records:
    """The messages of a rosbag2 SQLite file, in stamp order."""
    out = Ros2Records()
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            ids: dict[int, tuple[str, str]] = {}
            for tid, name, ty in db.execute("SELECT id, name, type FROM topics"):
                ids[tid] = (name, ty)
                out.topics[name] = ty
            tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master")}
            if "message_definitions" in tables:
                for ty, enc, text in db.execute(
                        "SELECT topic_type, encoding, encoded_message_definition "
                        "FROM message_definitions"):
                    if text:
                        out.definitions[ty] = (enc, text)
            for tid, n in db.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id"):
                if tid in ids:
                    out.counts[ids[tid][0]] = int(n)
            keep = [tid for tid, (_, ty) in ids.items() if wanted(ty)]
            marks = ",".join("?" * len(keep))
            for tid, t, data in db.execute(
                    f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN "
                    f"({marks}) ORDER BY timestamp, id", keep):
                out.messages.append((*ids[tid], int(t), bytes(data)))
    except sqlite3.Error as e:
        raise BagError(f"{path}: not a readable rosbag2 SQLite file ({e})") from None
    return out
