"""Opening a bag: its topics, and its messages of some topics in order, whatever reads it.

ROS 2 bags (a folder with ``metadata.yaml``; SQLite or MCAP storage) and indexed ROS 1 bags are
read by the rosbags library. A ROS 1 bag whose index rosbags cannot read (an early writer's,
a bag cut short while recording, a truncated copy) is read record by record in file order
(``server.offline.logs.bagfile``); its messages are decoded by rosbags from the bag's own message
definitions. Anything that stops a bag from being read becomes a ``BagError`` naming it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from server.offline.logs.bagfile import deserializer, read_records
from server.offline.logs.records import BagError

log = logging.getLogger(__name__)


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a ROS 2 bag folder (or a folder of ``.db3``/``.mcap`` files), or a ROS 2
    storage file."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(
            f.suffix in (".db3", ".mcap") for f in path.iterdir())
    return path.suffix in (".bag", ".mcap", ".db3")


@dataclass
class BagMessages:
    """What was read of a bag: ``topics`` (topic → (type, messages)), the messages of the
    chosen topics in order as (topic, type, receive time [ns], raw bytes), ``decode(raw,
    type)``, what read it and what could not be read."""

    topics: dict[str, tuple[str, int]]
    messages: list[tuple[str, str, int, bytes]]
    decode: Callable[[bytes, str], Any]
    reader: str
    lost: list[str] = field(default_factory=list)


Chooser = Callable[[dict[str, tuple[str, int]]], set[str]]


def _choose_noting(choose: Chooser, topics: dict[str, tuple[str, int]], lost: list[str]
                   ) -> set[str]:
    """``choose(topics)``; a refusal also says what part of the bag could not be read."""
    try:
        return choose(topics)
    except BagError as e:
        if not lost:
            raise
        raise BagError(f"{e}; the bag is damaged: {lost[0]}") from None


def _ros2_files(path: Path) -> list[Path]:
    """The storage files of a ROS 2 bag folder (or the one file given), in name order."""
    if path.is_file():
        return [path]
    return sorted(f for f in path.iterdir() if f.suffix in (".mcap", ".db3"))


def _with_ros2_files(path: Path, why: str, wanted: Callable[[str], bool],
                     choose: Chooser) -> BagMessages:
    from server.offline.logs.ros2files import Ros2Records, read_db3, read_mcap

    files = _ros2_files(path)
    if not files:
        raise BagError(f"{path}: a ROS 2 bag folder without .mcap or .db3 files ({why})")
    got = Ros2Records()
    for f in files:
        part = read_mcap(f, wanted) if f.suffix == ".mcap" else read_db3(f, wanted)
        for topic, ty in part.topics.items():
            got.topics.setdefault(topic, ty)
            got.counts[topic] = got.counts.get(topic, 0) + part.counts.get(topic, 0)
        got.messages += part.messages
        got.definitions.update(part.definitions)
        got.lost += [f"{f.name}: {w}" for w in part.lost]
    topics = {t: (ty, got.counts.get(t, 0)) for t, ty in got.topics.items()}
    chosen = _choose_noting(choose, topics, got.lost)
    messages = [m for m in got.messages if m[0] in chosen]
    return BagMessages(topics, messages, got.decoder(), f"storage files in file order ({why})",
                       got.lost)


def _with_rosbags(path: Path, choose: Chooser) -> BagMessages:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        topics = {t: (i.msgtype or "", int(i.msgcount)) for t, i in reader.topics.items()}
        chosen = choose(topics)
        conns = [c for c in reader.connections if c.topic in chosen]
        messages = [(c.topic, c.msgtype, int(t), bytes(raw))
                    for c, t, raw in (reader.messages(connections=conns) if conns else ())]
        kind = "rosbags (ROS 2)" if reader.is2 else "rosbags (ROS 1, indexed)"
        store = reader.typestore
        decode = store.deserialize_cdr if reader.is2 else store.deserialize_ros1
    return BagMessages(topics, messages, decode, kind)


def _with_records(path: Path, why: str, wanted: Callable[[str], bool],
                  choose: Chooser) -> BagMessages:
    rec = read_records(path, wanted)
    topics: dict[str, tuple[str, int]] = {}
    for c in rec.connections.values():
        ty, n = topics.get(c.topic, (c.msgtype, 0))
        topics[c.topic] = (ty if ty == c.msgtype else "", n + rec.counts.get(c.id, 0))
    chosen = _choose_noting(choose, topics, rec.lost)
    messages = [(c.topic, c.msgtype, t, raw) for c, t, raw in
                ((rec.connections[k], t, raw) for k, t, raw in rec.messages)
                if c.topic in chosen]
    return BagMessages(topics, messages, deserializer(rec), f"records in file order ({why})",
                       rec.lost)


def read_messages(path: Path, wanted: Callable[[str], bool], choose: Chooser) -> BagMessages:
    """The messages of the topics ``choose`` picks from the bag's topics. ``wanted`` says
    which message types a record-by-record reading keeps before the choice."""
    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such file or folder")
    if path.is_file() and path.stat().st_size == 0:
        raise BagError(f"{path}: empty file, not a ROS bag")
    if path.suffix != ".bag" or path.is_dir():
        folder = path if path.is_dir() else path.parent
        if not (folder / "metadata.yaml").is_file():
            return _with_ros2_files(path, "no metadata.yaml", wanted, choose)
        try:
            return _with_rosbags(folder, choose)
        except BagError:
            raise
        except Exception as e:   # a damaged database or MCAP file, a bag cut short
            why = f"rosbags cannot read it: {_what(e)}"
        log.info("%s: %s; reading its storage files in file order", path, why)
        return _with_ros2_files(path, why, wanted, choose)
    try:
        return _with_rosbags(path, choose)
    except BagError:
        raise
    except Exception as e:   # rosbags fails on such bags in many ways
        why = f"its index cannot be read: {_what(e)}"
        log.info("%s: %s; reading it record by record", path, why)
    return _with_records(path, why, wanted, choose)


def _what(e: Exception) -> str:
    return f"{type(e).__name__}: {e}" if str(e) else type(e).__name__
