"""A sweep of (angle, range) samples onto fixed beams, losing as few samples as possible.

Nearest-beam binning loses samples whenever the samples sit half a beam off the beam angles:
with one sample per degree at 0.5°, 1.5°, … and one beam per degree, rounding sends two samples
to one beam and none to the next, so every other beam reads "no return" (issue 20, item 7).

``to_beams`` starts from nearest-beam binning, then fills each beam that received no sample
while both its neighbours did (a lone empty beam between samples is an artefact of rounding; two
or more empty beams in a row are a gap in the data) from the nearest beam that received two or
more: every beam in between passes its sample one beam along toward the empty one. A move is
allowed only while the sample stays within ``max_shift`` beams (default 1) of its own angle,
and a chain never crosses an empty beam, so a real gap stays empty: no range is made up.
Where several samples still share a beam the nearest return wins (the conservative reading for
mapping and collision avoidance), so every sample is kept or covered by a nearer return within
``max_shift`` beams of its angle.
"""

from __future__ import annotations

import bisect
import math

import numpy as np


def to_beams(angles_rad: np.ndarray, ranges: np.ndarray, beams: int,
             max_shift: float = 1.0) -> np.ndarray:
    """Ranges on ``beams`` beams at ``-π + k·2π/beams`` (``inf``: no return).

    ``angles_rad`` any real angles (wrapped here); ``ranges`` in any unit, ``inf`` or NaN for a
    sample without a return (it still occupies a beam). Samples with a non-finite angle are
    dropped.
    """
    angles = np.asarray(angles_rad, dtype=float)
    values = np.asarray(ranges, dtype=float)
    keep = np.isfinite(angles)
    angles, values = angles[keep], np.where(np.isnan(values[keep]), np.inf, values[keep])
    # position in beams from beam 0, in [0, beams); the offset d from the nearest beam's
    # centre is in [-0.5, 0.5)
    pos = np.remainder((angles + math.pi) * (beams / (2 * math.pi)), beams)
    nearest = np.rint(pos).astype(np.int64)
    offsets = pos - nearest
    nearest %= beams
    out = np.full(beams, np.inf)
    np.minimum.at(out, nearest, values)
    counts = np.bincount(nearest, minlength=beams)
    if counts.all() or beams < 3:
        return out               # every beam has a sample (dense data): nothing to move
    order = np.lexsort((offsets, nearest))
    members: list[list[tuple[float, float]]] = [[] for _ in range(beams)]
    for b, d, r in zip(nearest[order].tolist(), offsets[order].tolist(),
                       values[order].tolist(), strict=True):
        members[b].append((d, r))
    lone = (counts == 0) & (np.roll(counts, 1) > 0) & (np.roll(counts, -1) > 0)
    changed: set[int] = set()
    for hole in np.flatnonzero(lone).tolist():
        chain = _nearest_chain(members, hole, max_shift)
        if chain is not None:
            changed.update(_pass_along(members, hole, *chain))
    for b in changed:
        out[b] = min(r for _, r in members[b])
    return out


def _nearest_chain(members: list[list[tuple[float, float]]], hole: int,
                   max_shift: float) -> tuple[int, int] | None:
    """(direction, length) of the shortest chain that can fill ``hole``: beams
    ``hole + direction·1 … hole + direction·length``, the last holding two or more samples, each
    passing one sample toward the hole within ``max_shift``; None when there is none.

    Both sides are searched a beam at a time, so the search ends at the nearest donor; a side
    ends at an empty beam (a gap: nothing passes across it) or a sample that may not move."""
    beams = len(members)
    alive = [-1, 1]
    for step in range(1, beams):
        for direction in list(alive):
            m = members[(hole + direction * step) % beams]
            # the sample on the hole's side would move one beam toward it
            d = (m[-1][0] - 1.0 if direction < 0 else m[0][0] + 1.0) if m else math.inf
            if abs(d) > max_shift:
                alive.remove(direction)
            elif len(m) >= 2:
                return direction, step
        if not alive:
            break
    return None


def _pass_along(members: list[list[tuple[float, float]]], hole: int, direction: int,
                length: int) -> list[int]:
    """Each beam of the chain passes its sample on the hole's side one beam toward it;
    returns the beams whose samples changed."""
    beams = len(members)
    for step in range(1, length + 1):
        src = members[(hole + direction * step) % beams]
        dst = members[(hole + direction * (step - 1)) % beams]
        if direction < 0:        # from the lower beam: its highest offset moves up
            d, r = src.pop()
            bisect.insort(dst, (d - 1.0, r))
        else:                    # from the higher beam: its lowest offset moves down
            d, r = src.pop(0)
            bisect.insort(dst, (d + 1.0, r))
    return [(hole + direction * step) % beams for step in range(length + 1)]
