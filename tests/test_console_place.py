"""Placing a robot by hand from the console's page (a real headless browser): the robot's row
says it is searching, *place…* shows the known map, and a press where the robot stands
dragged toward where it faces places it — the order carried out by a real core on a known map
(the small house surveyed), whose outputs feed the console as the bus would."""

from __future__ import annotations

import math
from collections.abc import Iterator
from concurrent.futures import Future
from typing import Any

import numpy as np
import pytest

from bench.support.known_mission import WORLDS, KnownMission, demo_config, free_poses, mission
from bench.support.survey import survey_map
from mrslam.browser import BrowserUnavailable, ConsolePage, chromium_path
from schemas import keys
from schemas.codec import encode
from server.command.operator import OperatorCommand
from server.console.service import Console
from server.knownmap.ghosts import MAP_TEAM
from tests.console_support import TOKEN

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

try:
    chromium_path()
    NO_BROWSER = ""
except BrowserUnavailable as e:
    NO_BROWSER = str(e)

WORLD = WORLDS / "small_house.world"


def publish(console: Console, m: KnownMission) -> None:
    """The core's outputs to the console, as the node publishes them on the bus."""
    stamp = int(m.sim_time_s * 1e9)
    for msg in m.core.map_updates():
        console._arrived(keys.SERVER_MAP, encode(msg))
    console._arrived(keys.SERVER_ROBOTS, encode(m.core.robot_states(stamp)))
    for ev in m.core.pop_events():
        console._arrived(keys.SERVER_EVENTS, encode(ev))


@pytest.fixture
def console() -> Iterator[tuple[Console, KnownMission]]:
    known = survey_map(WORLD, spacing_m=1.5)
    cfg = demo_config(confirmations=1000, query_period_s=100.0)   # never placed by itself
    spawn = free_poses(WORLD, 1, np.random.default_rng(3))
    m = mission(WORLD, known, {"r1": spawn[0]}, cfg, np.zeros(3))
    m.run_until(3.0)

    def operate(cmd: OperatorCommand) -> Future[Any]:
        f: Future[Any] = Future()
        f.set_result(m.core.operate(cmd, int(m.sim_time_s * 1e9)))
        publish(c, m)
        return f

    c = Console(0, operate, lambda: {"scans": {}, "dropped": {},
                                     "orders": m.core.orders.view()}, token=TOKEN)
    try:
        publish(c, m)
        yield c, m
    finally:
        c.close()


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)
def test_a_press_and_drag_on_the_known_map_places_a_searching_robot(
        console: tuple[Console, KnownMission]) -> None:
    c, m = console
    row = "document.querySelector('[data-testid=\"robot-row-r1\"]')"
    with ConsolePage(c.url) as cp:
        page = cp.page
        cp.wait_for(f"{row} && {row}.dataset.localisation === 'searching'", 60)
        cp.wait_for("(window.mrslam.state.robots.r1.hypotheses || []).length > 0", 30)
        assert page.get_by_test_id("place-r1").is_visible()
        page.get_by_test_id("place-r1").click()
        cp.wait_for(f"window.mrslam.state.team === '{MAP_TEAM}' && "
                    "window.mrslam.knownCells() > 100", 60)
        # press 0.3 m from where it stands, drag 1 m toward (10° off) where it faces
        x, y, th = (float(v) for v in m.sim.robots["r1"].pose)
        x0, y0, th0 = x + 0.3, y - 0.2, th + math.radians(10)
        a = page.evaluate(f"() => window.mrslam.pagePoint({x0}, {y0})")
        b = page.evaluate(f"() => window.mrslam.pagePoint({x0 + math.cos(th0)}, "
                          f"{y0 + math.sin(th0)})")
        page.evaluate("() => { window.mrslam.lastAnswer = undefined; }")
        page.mouse.move(a[0], a[1])
        page.mouse.down()
        page.mouse.move(b[0], b[1], steps=6)
        page.mouse.up()
        cp.wait_for("window.mrslam.lastAnswer !== undefined", 60)
        answer = page.evaluate("() => window.mrslam.lastAnswer")
        assert answer["status"] == 200 and answer["ok"] is True, answer
        assert "place r1 by hand" in answer["message"] and "refined" in answer["message"]
        cp.wait_for(f"{row}.dataset.localisation === 'placed'", 60)
        assert not page.get_by_test_id("place-r1").is_visible()
        page.locator('[data-testid="event"][data-kind="robot_joined"]',
                     has_text="by hand").first.wait_for(timeout=60_000)
    assert m.core.robots["r1"].team_id == MAP_TEAM
    err_m, err_deg = m.error("r1")
    assert err_m <= 0.10 and err_deg <= 1.0
