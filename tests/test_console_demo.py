"""The console against the running demo, in a real browser: the page shows the three robots
and a map that grows; STOP ALL takes every robot's commanded and simulated velocity to zero and
holds it there; Resume all lets them explore again, the run still reaches its threshold, and
the page as it ended is saved in the run folder. (How fast: ``bench/console.py``.)"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from bench.support.console_demo import DemoRun, first_moving_after, moving, zero_after
from mrslam.browser import BrowserUnavailable, ConsolePage, chromium_path
from tests.console_support import free_port

pytestmark = pytest.mark.e2e

ROBOTS = ["r1", "r2", "r3"]

try:
    chromium_path()
    NO_BROWSER = ""
except BrowserUnavailable as e:
    NO_BROWSER = str(e)


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)
@pytest.mark.timeout(1200)
def test_stop_all_from_the_page_stops_the_demo_and_resume_lets_it_finish(
        tmp_path: Path) -> None:
    demo = DemoRun(tmp_path / "run", free_port())
    watch = demo.watch()
    try:
        with ConsolePage(demo.url) as cp:
            for rid in ROBOTS:
                cp.page.get_by_test_id(f"robot-row-{rid}").wait_for(timeout=180_000)
            cp.wait_for("window.mrslam.knownCells() > 0", 180)
            first = cp.page.evaluate("() => window.mrslam.knownCells()")
            cp.wait_for(f"window.mrslam.knownCells() > {first}", 180)   # the map grows

            # wait until every robot is being driven, then stop them all from the page
            def all_moving(since: float) -> bool:
                return {s[1] for s in watch.samples("commands", since) if moving(s)} \
                    >= set(ROBOTS)

            t = time.time()
            deadline = time.monotonic() + 300
            while not all_moving(t) and time.monotonic() < deadline:
                time.sleep(0.2)
            assert all_moving(t), "the robots never all moved"
            t_click = time.time()
            cp.page.get_by_test_id("stop-all").click()
            cp.page.get_by_test_id("held-banner").wait_for(state="visible", timeout=60_000)
            # held: from some moment on, every command and every simulated velocity is zero,
            # and stays so for 5 s of wall time with the simulation going on
            sim_at = watch.sim_time_s
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                now = time.time()
                zero = zero_after(watch.samples("commands", t_click), ROBOTS, t_click, now)
                still = zero_after(watch.samples("sim", t_click), ROBOTS, t_click, now)
                settled = [v for v in [*zero.values(), *still.values()] if v is not None]
                if len(settled) == 2 * len(ROBOTS) and now - t_click - max(settled) >= 5.0:
                    break
                time.sleep(0.2)
            else:
                pytest.fail(f"never held at zero: {zero}, {still}")
            assert watch.sim_time_s > sim_at            # the simulation went on meanwhile
            rows = [cp.page.get_by_test_id(f"robot-row-{rid}") for rid in ROBOTS]
            assert [r.get_attribute("data-mode") for r in rows] == ["idle"] * 3

            t_resume = time.time()
            cp.page.get_by_test_id("resume-all").click()
            deadline = time.monotonic() + 120
            while first_moving_after(watch.samples("commands", t_resume), t_resume) is None:
                assert time.monotonic() < deadline, "the robots never moved again"
                time.sleep(0.1)
            assert demo.wait(timeout_s=900) == 0
    finally:
        watch.close()
        demo.stop()
    report = json.loads((demo.run / "report.json").read_text())
    assert report["reached"] is True
    assert (demo.run / "console.png").stat().st_size > 10_000
    events = report["events"]
    assert any(e["kind"] == "operator" and "stop every robot" in e["message"] for e in events)
    assert any(e["kind"] == "operator" and "resume every robot" in e["message"]
               for e in events)
