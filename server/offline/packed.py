"""A long log's scans, read without their ranges, packed into a few arrays.

Read as records (``LaserRecord`` with its poses, an ``OdometryScan`` around it), a scan takes
about 700 bytes in many small objects: 21 MB for a 91-minute log. Freed one by one as the
scans are fed, that memory came back to the SLAM only in part (the allocator's pools stay
held by the objects around them), so a long log's peak carried most of it to the end.
Packed, a scan takes about 60 bytes, and the records are freed all at once before the first
scan is fed. ``PackedScans[i]`` makes scan i's record again (without ranges, as read, and
without its poses: the odometry is attached, ``T_odom_laser``)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol, overload

import numpy as np
from numpy.typing import NDArray

from server.offline.logs import LaserRecord, OdometryScan
from server.offline.logs.carmen import NO_RANGES
from server.offline.logs.records import F64


class _Scan(Protocol):
    @property
    def record(self) -> LaserRecord: ...
    @property
    def T_odom_laser(self) -> F64 | None: ...


@dataclass(frozen=True, slots=True)
class _Bare:
    record: LaserRecord
    T_odom_laser: None = None


class PackedScans(Sequence[OdometryScan | _Bare]):
    """Scans (each with ``record`` and ``T_odom_laser``, or None) packed; ``scans[i] = None``
    (``process(release=True)``) holds nothing to free, and is accepted."""

    def __init__(self, scans: Sequence[_Scan]) -> None:
        n = len(scans)
        kinds: dict[str, int] = {}
        angles: dict[int, int] = {}
        self._angles: list[F64] = []
        self._kind = np.zeros(n, dtype=np.int16)
        self._angle = np.zeros(n, dtype=np.int32)
        self.stamps_s = np.zeros(n)
        self._line = np.zeros(n, dtype=np.int64)
        self._max = np.full(n, np.nan)
        self._odom = np.full((n, 3), np.nan)
        texts = []
        for i, s in enumerate(scans):
            r = s.record
            self._kind[i] = kinds.setdefault(r.kind, len(kinds))
            a = angles.get(id(r.angles_rad))
            if a is None:
                a = angles[id(r.angles_rad)] = len(self._angles)
                self._angles.append(r.angles_rad)
            self._angle[i] = a
            self.stamps_s[i] = r.stamp_s
            self._line[i] = r.line_no
            if r.max_range_m is not None:
                self._max[i] = r.max_range_m
            if s.T_odom_laser is not None:
                self._odom[i] = s.T_odom_laser
            texts.append(r.stamp_text)
        self._kinds = list(kinds)
        coded = [t.encode() for t in texts]
        self._text = b"".join(coded)
        self._text_end = np.cumsum([len(c) for c in coded], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.stamps_s)

    def stamp_text(self, i: int) -> str:
        """Scan i's stamp as written in the log."""
        start = int(self._text_end[i - 1]) if i > 0 else 0
        return self._text[start:int(self._text_end[i])].decode()

    def _record(self, i: int) -> LaserRecord:
        text = self.stamp_text(i)
        m = float(self._max[i])
        return LaserRecord(self._kinds[self._kind[i]], text, float(self.stamps_s[i]), NO_RANGES,
                           self._angles[self._angle[i]], None if np.isnan(m) else m, None,
                           None, int(self._line[i]))

    @overload
    def __getitem__(self, i: int) -> OdometryScan | _Bare: ...
    @overload
    def __getitem__(self, i: slice) -> list[OdometryScan | _Bare]: ...

    def __getitem__(self, i: int | slice) -> OdometryScan | _Bare | list[OdometryScan | _Bare]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        rec = self._record(i)
        T = self._odom[i]
        if np.isnan(T[0]):
            return _Bare(rec)
        return OdometryScan(rec, T.copy())

    def __setitem__(self, i: int, value: None) -> None:
        """Releasing a scan fed (``process(release=True)``): nothing is held per scan."""

    def __iter__(self) -> Iterator[OdometryScan | _Bare]:
        return (self[i] for i in range(len(self)))

    @property
    def nbytes(self) -> int:
        arrays: list[NDArray[np.generic]] = [self._kind, self._angle, self.stamps_s, self._line,
                                             self._max, self._odom, self._text_end]
        return sum(a.nbytes for a in arrays) + len(self._text)


class StampTexts(Sequence[str]):
    """The stamps (as written) of some of a ``PackedScans``' scans, by index: a long log's
    29,000 stamps are not held as as many strings."""

    def __init__(self, scans: PackedScans, indices: Sequence[int]) -> None:
        self._scans = scans
        self._indices = np.asarray(indices, dtype=np.int64)

    def __len__(self) -> int:
        return len(self._indices)

    @overload
    def __getitem__(self, i: int) -> str: ...
    @overload
    def __getitem__(self, i: slice) -> list[str]: ...

    def __getitem__(self, i: int | slice) -> str | list[str]:
        if isinstance(i, slice):
            return [self._scans.stamp_text(int(j)) for j in self._indices[i]]
        return self._scans.stamp_text(int(self._indices[i]))

    def __iter__(self) -> Iterator[str]:
        return (self._scans.stamp_text(int(j)) for j in self._indices)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]
