"""Rows appended once per scan — a stamp, a small integer tag and a few floats — kept in
growing numpy columns rather than as a Python object per row: a robot adds 36,000 rows an hour,
and as objects they would cost memory, time to search and time to snapshot."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray


class StampedRows:
    """Rows (stamp_ns, tag, values[width]) in the order appended."""

    def __init__(self, width: int) -> None:
        self.width = width
        self._n = 0
        self._stamps = np.zeros(16, np.int64)
        self._tags = np.zeros(16, np.int64)
        self._values = np.zeros((16, width), np.float64)

    def append(self, stamp_ns: int, values: ArrayLike, tag: int = 0) -> None:
        if self._n == len(self._stamps):
            grow = max(16, self._n)
            self._stamps = np.concatenate([self._stamps, np.zeros(grow, np.int64)])
            self._tags = np.concatenate([self._tags, np.zeros(grow, np.int64)])
            self._values = np.concatenate([self._values, np.zeros((grow, self.width))])
        self._stamps[self._n] = stamp_ns
        self._tags[self._n] = tag
        self._values[self._n] = np.asarray(values, np.float64).reshape(self.width)
        self._n += 1

    def __len__(self) -> int:
        return self._n

    @property
    def stamps(self) -> NDArray[np.int64]:
        return self._stamps[:self._n]

    @property
    def tags(self) -> NDArray[np.int64]:
        return self._tags[:self._n]

    @property
    def values(self) -> NDArray[np.float64]:
        return self._values[:self._n]

    def row(self, i: int) -> tuple[int, int, NDArray[np.float64]]:
        """Row ``i``: its stamp, tag and a copy of its values."""
        return int(self._stamps[i]), int(self._tags[i]), self._values[i].copy()

    def __getstate__(self) -> dict[str, Any]:
        return {"width": self.width, "stamps": self.stamps.copy(), "tags": self.tags.copy(),
                "values": self.values.copy()}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.width = state["width"]
        self._stamps, self._tags = state["stamps"], state["tags"]
        self._values = state["values"].reshape(-1, self.width)
        self._n = len(self._stamps)
