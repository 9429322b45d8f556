"""The demo's progress bar ends on a line that says how the run ended, not on the last state
it saw while the run went on (it read "server restarting (0 so far)" when the server had just
finished well)."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import pytest
from rich.console import Console

from mrslam.launch import ProcessGroup
from mrslam.monitor import Monitor
from mrslam.supervise import RestartPolicy, Supervisor

#: starts other processes (tiny Python children standing in for the server and simulator)
pytestmark = pytest.mark.e2e


def last_line(endpoint: str, tmp_path: Path, server_code: str, restarts: int = 0
              ) -> tuple[str, str]:
    """Follow a run whose 'server' runs ``server_code`` and whose 'simulator' outlives it;
    why it ended, and the bar's last line."""
    group = ProcessGroup(tmp_path / "logs", command=(sys.executable, "-c"))
    with group:
        server = group.start("server", server_code)
        sim = group.start("sim", "import time; time.sleep(60)")
        out = io.StringIO()
        console = Console(file=out, width=240, force_terminal=False)
        with Monitor(endpoint, ["r1"]) as mon:
            why = mon.follow(Supervisor(group, server, RestartPolicy(restarts, 0.05)), sim,
                             wall_timeout_s=30.0, threshold=0.98, console=console,
                             progress=True)
    lines = [line for line in out.getvalue().splitlines() if line.strip()]
    return why, lines[-1]


def test_a_run_whose_server_finished_ends_on_finished(router: object, endpoint: str,
                                                      tmp_path: Path) -> None:
    why, line = last_line(endpoint, tmp_path, "import time; time.sleep(0.5)")
    assert why == "finished"
    assert "run finished" in line and "restarting" not in line


def test_a_run_whose_server_died_for_good_says_so(router: object, endpoint: str,
                                                  tmp_path: Path) -> None:
    why, line = last_line(endpoint, tmp_path, "import sys; sys.exit(3)", restarts=0)
    assert why == "server-died"
    assert "the server died for good (0 restart(s) spent)" in line
