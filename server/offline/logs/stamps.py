"""Stamps of a recorded log in the order they were written, made fit to process.

A log's lines are in the order the robot recorded them, but the stamps on them come from a
clock that may jitter, glitch or step. Three faults are seen in real logs:

- jitter: a scan stamped a few milliseconds before the one written above it (the Intel
  Research Lab log has hundreds). The scan is kept, in file order: a stamp less than
  ``jitter_fraction`` of the scan period behind the latest kept one is early, and it is fed
  ``EARLY_NUDGE_S`` after that one (the SLAM core needs stamps that do not go back), while
  its own stamp is what the outputs carry;
- one scan (or a few) stamped far ahead of its neighbours: dropping every later scan older
  than it would lose the rest of the run, so the outlier is what goes;
- the clock stepped back (NTP, a reboot) and stays there: the scans after the step are
  shifted forward (re-based) so that they follow the last good one by one typical period.

A scan is judged by the ``window`` scans after it: an ahead spike has most of them between the
last accepted stamp and its own; a real step back has most of them behind the last accepted
stamp too; a lone scan further behind than jitter is dropped. Forward jumps that the following
scans confirm are gaps in the recording and are kept as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

#: how far after the latest kept stamp an early (jittered) scan is fed [s]
EARLY_NUDGE_S = 1e-6


@dataclass
class StampPlan:
    """Which scans to use (indices in file order) and their stamps in one forward clock."""

    keep: list[int] = field(default_factory=list)
    stamps_s: list[float] = field(default_factory=list)
    dropped_ahead: list[int] = field(default_factory=list)
    dropped_behind: list[int] = field(default_factory=list)
    steps: list[tuple[int, float]] = field(default_factory=list)  # (index, shift [s])
    early: list[int] = field(default_factory=list)   # kept, a little behind the one before
    period_s: float = 0.0

    @property
    def dropped(self) -> int:
        return len(self.dropped_ahead) + len(self.dropped_behind)


def plan_stamps(stamps_s: Sequence[float], window: int = 5,
                jitter_fraction: float = 0.5) -> StampPlan:
    """Decide, scan by scan in file order, which stamps to keep, nudge or re-base."""
    s = np.asarray(stamps_s, dtype=np.float64)
    diffs = np.diff(s)
    forward = diffs[diffs > 0]
    period = float(np.median(forward)) if len(forward) else 0.0
    jitter = jitter_fraction * period
    plan = StampPlan(period_s=period)
    offset, last = 0.0, -np.inf
    for i, stamp in enumerate(s):
        t = stamp + offset
        following = s[i + 1:i + 1 + window] + offset
        most = len(following) / 2
        if t >= last:
            spike = (following < t).sum() > most and (following >= last).sum() > most
            if spike:
                plan.dropped_ahead.append(i)
                continue
        elif (following < last).sum() > most:   # the clock stepped back and stays there
            shift = last + period - t
            offset += shift
            t += shift
            plan.steps.append((i, shift))
        elif last - t <= jitter:                 # jitter: kept in file order, fed just after
            plan.early.append(i)
            t = last + EARLY_NUDGE_S
        else:
            plan.dropped_behind.append(i)
            continue
        plan.keep.append(i)
        plan.stamps_s.append(float(t))
        last = t
    return plan
