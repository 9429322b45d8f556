"""The console's page in a real headless browser (Debian's chromium driven by playwright)
against a real server with robots on the wire: it shows the robots and their map, its buttons
stop and resume them, a click on the map sends one somewhere, and without the token it shows
nothing at all."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from bench.support.fleet import RoomRobot
from mrslam.browser import BrowserUnavailable, ConsolePage, chromium_path
from tests.console_support import (
    TOKEN,
    commands_after,
    free_port,
    robots_moving_after,
    start_server,
    try_state,
)
from tests.waiting import within

pytestmark = pytest.mark.e2e

try:
    chromium_path()
    NO_BROWSER = ""
except BrowserUnavailable as e:
    NO_BROWSER = str(e)
needs_browser = pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)

Fleet = tuple[int, list[RoomRobot]]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    """One server and two robots for the module's tests (starting them takes a while)."""
    port = free_port()
    srv = start_server(tmp_path_factory.mktemp("console"), port)
    srv.client().close()
    robots = [RoomRobot(srv.endpoint, rid).start() for rid in ("r1", "r2")]
    try:
        assert within(lambda: len((try_state(port) or {}).get("robots", [])) == 2, 90)
        yield port, robots
    finally:
        for r in robots:
            r.close()
        srv.stop()


def url(port: int, token: str = TOKEN) -> str:
    return f"http://127.0.0.1:{port}/?token={token}"


@needs_browser
def test_the_page_shows_the_robots_and_their_map_and_its_buttons_work(fleet: Fleet) -> None:
    port, robots = fleet
    with ConsolePage(url(port)) as cp:
        page = cp.page
        for rid in ("r1", "r2"):
            page.get_by_test_id(f"robot-row-{rid}").wait_for(timeout=60_000)
        cp.wait_for("window.mrslam.stats.mapsDrawn > 0 && window.mrslam.knownCells() > 100", 60)
        canvas = page.get_by_test_id("map-canvas")
        assert canvas.bounding_box()["width"] > 300
        # the map is drawn: the canvas is not all one colour
        colours = page.evaluate("""() => {
            const c = document.querySelector('[data-testid="map-canvas"]');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
            const seen = new Set();
            for (let i = 0; i < d.length; i += 4 * 97) seen.add(d[i] + ',' + d[i+1] + ',' + d[i+2]);
            return seen.size; }""")
        assert colours >= 3
        assert page.get_by_test_id("status").inner_text() == "live"

        t0 = time.monotonic()
        assert within(lambda: all(robots_moving_after(robots, t0)), 60)
        page.get_by_test_id("stop-all").click()
        page.get_by_test_id("held-banner").wait_for(state="visible", timeout=60_000)
        t_stop = time.monotonic()
        for rid in ("r1", "r2"):
            row = page.get_by_test_id(f"robot-row-{rid}")
            cp.wait_for(f"document.querySelector('[data-testid=\"robot-row-{rid}\"]')"
                        f".dataset.held === '1'", 60)
            assert row.get_attribute("data-held") == "1"
        assert within(lambda: all(len(commands_after(r, t_stop)) >= 20 for r in robots), 60)
        assert all(set(commands_after(r, t_stop)) == {(0.0, 0.0)} for r in robots)

        page.get_by_test_id("resume-all").click()
        page.get_by_test_id("held-banner").wait_for(state="hidden", timeout=60_000)
        t_resume = time.monotonic()
        assert within(lambda: all(robots_moving_after(robots, t_resume)), 60)

        # one robot, from its row
        page.get_by_test_id("stop-r2").click()
        cp.wait_for("document.querySelector('[data-testid=\"robot-row-r2\"]')"
                    ".dataset.held === '1'", 60)
        assert page.get_by_test_id("robot-row-r1").get_attribute("data-held") == "0"
        page.get_by_test_id("resume-r2").click()
        cp.wait_for("document.querySelector('[data-testid=\"robot-row-r2\"]')"
                    ".dataset.held === '0'", 60)

        # a click on the map sends r1 a little way from where it is
        pose = page.evaluate("() => window.mrslam.state.robots.r1.pose")
        page.get_by_test_id("goto-r1").click()
        cp.wait_for("window.mrslam.state.team === window.mrslam.state.robots.r1.team_id", 60)
        xy = page.evaluate(f"() => window.mrslam.pagePoint({pose[0] + 0.4}, {pose[1]})")
        page.evaluate("() => { window.mrslam.lastAnswer = undefined; }")
        page.mouse.click(xy[0], xy[1])
        cp.wait_for("window.mrslam.lastAnswer !== undefined", 60)
        answer = page.evaluate("() => window.mrslam.lastAnswer")
        assert answer["status"] == 200 and answer["ok"] is True, answer
        assert "send r1 to" in answer["message"]
        page.locator('[data-testid="event"][data-kind="operator"]',
                     has_text="send r1 to").first.wait_for(timeout=60_000)


@needs_browser
def test_without_the_token_the_page_is_empty(fleet: Fleet) -> None:
    port, _ = fleet
    for token in ("", "not-the-token", TOKEN[:-1]):
        with ConsolePage(url(port, token), must_load=False) as cp:
            assert cp.last_status == 401, token
            assert cp.page.get_by_test_id("map-canvas").count() == 0
            assert cp.page.content().count("robot-row") == 0
            assert cp.page.evaluate("() => window.mrslam === undefined")
