"""Loop closure's likelihood fields, kept for every robot of the process within one bound.

A field (``server.slam.correlative.LikelihoodField``) is a submap's correlative look-up: eight
full-resolution levels of float32, about half a megabyte for a submap of the houses. It is
made again from the submap's points, the same bit for bit, in about 1.5 ms, so it is a cache:
never pickled, never part of the state.

Each robot's loop closer used to keep its own 8 MB of fields. With ten robots that was 69 MB
of the server's memory (``bench/snapshot_cost.py``, late in a mission), and a snapshot's fork
copies the page tables of all of the process's memory, about 3 ms per 100 MB here. Now the
process keeps one cache, shared by the closers and bounded as a whole (``TOTAL_BYTES``); each
closer also keeps its own bound within it (``LoopCloser.field_bytes``, ``FIELD_CACHE``
fields), so that one robot's searches do not push out every other robot's fields. The least
lately used field goes first. Few fields are found again anyway: in that bench's 300 s of ten
robots, 336 fields were made and 19 found with 12 MB for all; 295 and 60 with 24 MB. A field
made again costs about 1.5 ms, a few hundredths of a millisecond per scan.
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict

from server.slam.correlative import LikelihoodField

#: the fields of every closer in the process, at most (the newest one is always kept)
TOTAL_BYTES = 12 << 20

_owners = itertools.count(1)


def new_owner() -> int:
    """A number for a closer's fields, never given twice in a process (so a closer made after
    another is gone never finds the other's fields under its own submap indices)."""
    return next(_owners)


def _size(field: LikelihoodField) -> int:
    return sum(level.nbytes for level in field.pyramid)


class FieldCache:
    """Fields keyed by (owner, submap index), least lately used first."""

    def __init__(self, total_bytes: int = TOTAL_BYTES) -> None:
        self.total_bytes = total_bytes
        self._fields: OrderedDict[tuple[int, int], tuple[LikelihoodField, int]] = OrderedDict()
        self._held = 0
        self._lock = threading.Lock()      # robots may be served from more than one thread
        self.made = 0                      # fields made (a miss) ...
        self.reused = 0                    # ... and found (a hit), for the benches

    @property
    def held_bytes(self) -> int:
        return self._held

    def __len__(self) -> int:
        return len(self._fields)

    def get(self, owner: int, index: int) -> LikelihoodField | None:
        with self._lock:
            entry = self._fields.get((owner, index))
            if entry is None:
                return None
            self._fields.move_to_end((owner, index))
            self.reused += 1
            return entry[0]

    def put(self, owner: int, index: int, field: LikelihoodField, owner_bytes: int,
            owner_count: int) -> None:
        """Keep ``field``; then drop the least lately used fields, first the owner's beyond
        its own bounds, then anyone's beyond the total. The field just kept stays."""
        size = _size(field)
        key = (owner, index)
        with self._lock:
            self.made += 1
            if (old := self._fields.pop(key, None)) is not None:
                self._held -= old[1]
            self._fields[key] = (field, size)
            self._held += size
            mine = [(k, n) for k, (_, n) in self._fields.items() if k[0] == owner]
            count, held_mine = len(mine), sum(n for _, n in mine)
            for k, n in mine[:-1]:
                if count <= owner_count and held_mine <= owner_bytes:
                    break
                del self._fields[k]
                self._held -= n
                held_mine -= n
                count -= 1
            while self._held > self.total_bytes and len(self._fields) > 1:
                k, (_, n) = next(iter(self._fields.items()))
                if k == key:
                    break
                del self._fields[k]
                self._held -= n


#: the process's cache
FIELDS = FieldCache()
