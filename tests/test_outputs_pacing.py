"""Outputs rewritten whole every period would cost more and more CPU as a mission's
trajectories grow; past 4 % of a core, the rounds come less often."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from server.planning import OccupancyGrid as PlanningGrid
from server.runtime.outputs import OUTPUTS_CPU_SHARE, OutputPacer, Outputs


def _outputs(robots: int, poses: int) -> Outputs:
    rng = np.random.default_rng(0)
    stamps = np.arange(poses, dtype=np.int64) * 100_000_000 + 1_700_000_000_000_000_000
    grid = PlanningGrid(np.zeros((20, 20), np.int8), 0.05, (0.0, 0.0))
    trajectories = {f"r{i}_{kind}": (stamps, rng.normal(size=(poses, 3)))
                    for i in range(robots) for kind in ("online", "final")}
    return Outputs({"t1": grid}, {"t1": lambda: rng.normal(size=(10, 2))}, trajectories,
                   {"robots": {}})


def test_small_outputs_keep_the_period(tmp_path: Path) -> None:
    pacer = OutputPacer(0.5)
    out = _outputs(2, 100)
    pacer.timed_write(lambda: out.write(tmp_path))()
    assert 0.0 < pacer.write_cpu_s < 0.5 * OUTPUTS_CPU_SHARE
    assert pacer.next_in() == 0.5
    assert (tmp_path / "trajectories" / "r1_final.tum").read_text().count("\n") == 100


def test_a_long_missions_outputs_come_less_often(tmp_path: Path) -> None:
    """Three robots' half hour at 10 Hz: the round costs about a second of CPU, so at most
    4 % of a core puts the next one some 25 s later, not 10 s."""
    pacer = OutputPacer(10.0)
    out = _outputs(3, 18_000)
    pacer.timed_write(lambda: out.write(tmp_path))()
    assert pacer.write_cpu_s > 0.5 * OUTPUTS_CPU_SHARE * 10.0
    assert pacer.next_in() > 10.0
    assert abs(pacer.next_in() * OUTPUTS_CPU_SHARE - pacer.write_cpu_s) < 1e-9
    pacer.gather_cpu_s = 1.0
    assert abs(pacer.next_in() * OUTPUTS_CPU_SHARE - (1.0 + pacer.write_cpu_s)) < 1e-9


def test_a_failed_write_still_counts_its_cost() -> None:
    pacer = OutputPacer(10.0)

    def fails() -> None:
        sum(i * i for i in range(200_000))
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        pacer.timed_write(fails)()
    assert pacer.write_cpu_s > 0.0
