"""The demo restarts a server that dies, as systemd would: first the supervisor with tiny
Python children, then a whole demo whose server is killed with SIGKILL mid-run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mrslam.launch import ProcessGroup
from mrslam.supervise import MAX_BACK_OFF_S, RestartPolicy, State, Supervisor

#: starts other processes: the e2e tier
pytestmark = pytest.mark.e2e

#: dies by SIGKILL on its first run (no marker file yet), then prints and exits 0
KILLED_ONCE = """
import os, signal, sys
from pathlib import Path
marker = Path(sys.argv[1])
if not marker.exists():
    marker.write_text("ran")
    print("first run", flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
print("second run", flush=True)
"""


def poll_until(sup: Supervisor, states: set[State], timeout_s: float = 20.0) -> State:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        state = sup.poll(sim_time_s=12.5)
        if state in states:
            return state
        time.sleep(0.01)
    raise AssertionError(f"supervisor never reached {states}")


def test_a_child_killed_once_is_restarted_then_its_clean_exit_is_done(tmp_path: Path) -> None:
    group = ProcessGroup(tmp_path / "logs", command=(sys.executable, "-c", KILLED_ONCE))
    child = group.start("server", str(tmp_path / "marker"))
    first_pid = child.pid
    sup = Supervisor(group, child, RestartPolicy(max_restarts=5, back_off_s=0.05))
    assert poll_until(sup, {"done"}) == "done"
    assert [(e.pid, e.exit_code, e.signal, e.restarted) for e in sup.exits] == \
        [(first_pid, -9, "SIGKILL", True)]
    ex = sup.exits[0]
    assert ex.sim_time_s == 12.5 and ex.back_off_s == 0.05
    assert ex.new_pid == child.pid != first_pid
    assert ex.restarted_at is not None and ex.restarted_at - ex.exited_at >= 0.05
    log = child.log_path.read_text()   # one log, both runs, the restart marked between them
    assert log.index("first run") < log.index("restarted after exit code -9") < \
        log.index("second run")


def test_restarts_stop_when_the_budget_is_spent_and_back_off_doubles(tmp_path: Path) -> None:
    group = ProcessGroup(tmp_path / "logs", command=(sys.executable, "-c", "raise SystemExit(3)"))
    child = group.start("server")
    sup = Supervisor(group, child, RestartPolicy(max_restarts=2, back_off_s=0.02))
    assert poll_until(sup, {"failed"}) == "failed"
    assert [(e.exit_code, e.signal, e.restarted, e.back_off_s) for e in sup.exits] == \
        [(3, None, True, 0.02), (3, None, True, 0.04), (3, None, False, None)]
    assert sup.poll() == "failed" and len(sup.exits) == 3   # noted once
    assert sup.restarts == 2


def test_a_child_its_group_stops_is_not_restarted(tmp_path: Path) -> None:
    group = ProcessGroup(tmp_path / "logs",
                         command=(sys.executable, "-c", "import time; time.sleep(60)"))
    child = group.start("server")
    sup = Supervisor(group, child, RestartPolicy(back_off_s=0.01))
    assert sup.poll() == "running"
    group.stop(["server"], timeout_s=5.0)
    assert child.popen.returncode == -signal.SIGTERM
    assert sup.poll() == "done" and sup.exits == []


def test_a_restart_still_due_when_the_group_stops_is_dropped(tmp_path: Path) -> None:
    group = ProcessGroup(tmp_path / "logs", command=(sys.executable, "-c", "raise SystemExit(3)"))
    child = group.start("server")
    sup = Supervisor(group, child, RestartPolicy(back_off_s=20.0))
    assert poll_until(sup, {"restarting"}) == "restarting"
    group.stop(["server"])
    assert sup.poll() == "done"
    (ex,) = sup.exits
    assert ex.back_off_s == 20.0 and not ex.restarted and ex.new_pid is None


def test_back_off_doubles_up_to_its_cap() -> None:
    policy = RestartPolicy(max_restarts=10, back_off_s=1.0)
    waits = [policy.back_off(k) for k in range(8)]
    assert waits[:5] == [1.0, 2.0, 4.0, 8.0, 16.0]
    assert max(waits) == MAX_BACK_OFF_S and waits == sorted(waits)


def server_pids(run: Path, parent: int) -> list[int]:
    """Children of ``parent`` running ``mrslam server -c <run>/server.yaml``. A snapshot the
    server forks has the same command line, so only the demo's own children count."""
    found = subprocess.run(["pgrep", "-P", str(parent), "-f",
                            f"mrslam server -c {run / 'server.yaml'}"],
                           capture_output=True, text=True, check=False)
    return [int(p) for p in found.stdout.split()]


def sim_time_s(run: Path) -> float:
    """The simulated time of the last complete line of ``sim/truth.jsonl`` (0 before one)."""
    try:
        with (run / "sim" / "truth.jsonl").open("rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - 65536))
            lines = f.read().splitlines()
    except FileNotFoundError:
        return 0.0
    for line in reversed(lines):
        try:
            return float(json.loads(line)["stamp_ns"]) * 1e-9
        except (ValueError, KeyError):
            continue
    return 0.0


def kill_server_at(run: Path, demo: subprocess.Popen[bytes], at_sim_s: float) -> int:
    """SIGKILL the demo's server once the simulation passes ``at_sim_s``; its pid."""
    t0 = time.monotonic()
    while sim_time_s(run) < at_sim_s:
        assert demo.poll() is None, demo.communicate()[0].decode()
        assert time.monotonic() - t0 < 180, f"the simulation never reached {at_sim_s} s"
        time.sleep(0.2)
    (victim,) = server_pids(run, demo.pid)
    os.kill(victim, signal.SIGKILL)
    return victim


def demo_killed_at(run: Path, at_sim_s: float, *args: str) -> tuple[int, int, str]:
    """Run ``mrslam demo ARGS`` into ``run`` and kill its server at ``at_sim_s``: the killed
    pid, the demo's exit code and its output."""
    demo = subprocess.Popen([sys.executable, "-m", "mrslam", "demo", "--no-record",
                             "--out", str(run), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        victim = kill_server_at(run, demo, at_sim_s)
        output = demo.communicate(timeout=420)[0].decode()
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    return victim, demo.returncode, output


def test_the_demo_restarts_a_server_killed_mid_run(tmp_path: Path) -> None:
    run = tmp_path / "run"
    victim, code, output = demo_killed_at(run, 15.0, "--max-sim-time", "100")
    assert code in (0, 1), output   # the run may fall short, but it is a run
    report = json.loads((run / "report.json").read_text())
    (restart,) = report["server_restarts"]
    assert restart["pid"] == victim and restart["signal"] == "SIGKILL"
    assert restart["restarted"] and restart["new_pid"] not in (None, victim)
    assert restart["sim_time_s"] >= 15.0
    # the restarted server came back and commanded the robots again
    assert restart["up_after_s"] is not None and restart["first_command_after_s"] is not None
    assert report["exit_codes"]["server"] in (0, -signal.SIGTERM)
    assert "server died (SIGKILL)" in output


def test_a_server_that_dies_for_good_still_leaves_a_report(tmp_path: Path) -> None:
    """No restarts allowed: the server killed early leaves no outputs (or only a periodic
    refresh); the demo still scores what it has and exits 1 (fell short), not 2."""
    run = tmp_path / "run"
    victim, code, output = demo_killed_at(run, 0.5, "--max-sim-time", "100",
                                          "--server-restarts", "0")
    assert code == 1, output
    report = json.loads((run / "report.json").read_text())
    assert report["end"] == "server-died" and not report["reached"]
    (death,) = report["server_restarts"]
    assert death["pid"] == victim and not death["restarted"]
    assert any(m.startswith("server/summary.json") for m in report["missing"]), report["missing"]
    assert set(report["robots"]) == {"r1", "r2", "r3"}   # from the simulator's truth
    assert "No such file" not in output and "missing or damaged" in output
