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
    """Five robots' hour at 10 Hz: the round costs one to three seconds of CPU (by the
    machine), so at most 4 % of a core puts the next one 25 s or more later, not 10 s."""
    pacer = OutputPacer(10.0)
    out = _outputs(5, 36_000)
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


def test_a_round_is_spread_between_its_files(tmp_path: Path) -> None:
    """The writing pauses between a team's files and each trajectory's, four times as long
    as each piece took (at most 20 % busy), so the worker gets the interpreter meanwhile."""
    import time

    from server.runtime.outputs import OUTPUTS_DUTY, Spread

    out = _outputs(2, 30_000)          # four trajectories of 30,000 poses: pieces of ms
    calls: list[float] = []
    spread = Spread()

    def pause() -> None:
        calls.append(time.monotonic())
        spread()

    t0 = time.monotonic()
    spread.begin()
    busy0 = time.thread_time()
    out.write(tmp_path, pause)
    wall, busy = time.monotonic() - t0, time.thread_time() - busy0
    assert len(calls) == 1 + 4          # one team, four trajectories
    assert busy > 0.05 and wall > busy / OUTPUTS_DUTY * 0.8
    assert (tmp_path / "trajectories" / "r1_final.tum").read_text().count("\n") == 30_000


def test_a_stopped_spread_pauses_no_more() -> None:
    import threading
    import time

    from server.runtime.outputs import Spread

    spread = Spread(duty=0.01)          # 99 times as long as each piece
    spread.begin()
    time.sleep(0.05)
    threading.Timer(0.1, spread.stop).start()
    t0 = time.monotonic()
    spread()                            # would wait about 5 s
    spread()
    assert time.monotonic() - t0 < 2.0
