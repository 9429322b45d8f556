"""A compressed log's text decompressed once for both of ``slam-log``'s passes.

``slam-log`` reads a log twice: all of it first without the scans' ranges (``read_log(...,
keep_ranges=False)``), then each scan's ranges again as it is fed (``LaserLines``). On a
compressed log the second pass decompressed it a second time: on ``aces`` (0.8 MB of bzip2,
8 MB of text) that was about 6 % of the run. ``KeptText`` keeps the decompressed bytes of the
first pass, up to ``cap`` bytes, for the second to read from memory; a longer log stops being
kept as soon as it passes the cap (nothing decompressed twice before that) and is read again
from its file as before, so that a long log's text is never all held.
"""

from __future__ import annotations

import io
from typing import IO

#: decompressed bytes kept at most: the logs of ``docs/real-data.md`` (4-10 MB of text, runs
#: peaking near 140 MB) are kept; a long log, whose run peaks near the 250 MB bound
#: (``aces-x4``: 33 MB of text), is not
KEEP_BYTES = 16 << 20


class KeptText:
    """The decompressed bytes of one pass over a log, if they were read to the end and fit
    in ``cap`` bytes (``complete``); ``drop`` frees them."""

    def __init__(self, cap: int = KEEP_BYTES) -> None:
        self.cap = cap
        self.data: bytearray | None = bytearray()
        self.complete = False

    def add(self, chunk: memoryview) -> None:
        if self.data is None:
            return
        if len(self.data) + len(chunk) > self.cap:
            self.data = None           # too long: the second pass reads the file again
            return
        self.data += chunk

    def finish(self) -> None:
        """The pass read the stream to its end (not when it stopped on an error)."""
        self.complete = self.data is not None

    def drop(self) -> None:
        self.data = None
        self.complete = False

    def reader(self) -> IO[bytes] | None:
        """The kept bytes as a binary stream (None if not kept whole)."""
        if not self.complete or self.data is None:
            return None
        return io.BufferedReader(_Memory(memoryview(self.data)))


class Keeping(io.RawIOBase):
    """A binary stream read through, its bytes given to ``kept`` as they are read."""

    def __init__(self, raw: IO[bytes], kept: KeptText) -> None:
        self._raw = raw
        self._kept = kept

    def readable(self) -> bool:
        return True

    def readinto(self, b: bytearray | memoryview) -> int:  # type: ignore[override]
        n = self._raw.readinto(b)  # type: ignore[attr-defined]
        if n:
            self._kept.add(memoryview(b)[:n])
        elif n == 0:
            self._kept.finish()
        return int(n or 0)

    def close(self) -> None:
        self._raw.close()
        super().close()


class _Memory(io.RawIOBase):
    """A binary stream over bytes held in memory, without copying them first."""

    def __init__(self, data: memoryview) -> None:
        self._data = data
        self._at = 0

    def readable(self) -> bool:
        return True

    def readinto(self, b: bytearray | memoryview) -> int:  # type: ignore[override]
        n = min(len(b), len(self._data) - self._at)
        memoryview(b)[:n] = self._data[self._at:self._at + n]
        self._at += n
        return n

    def close(self) -> None:
        self._data.release()
        super().close()
