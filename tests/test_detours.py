"""Detours priced (server.fleet.rates, pricing, detours): the arithmetic of a price, a declined
detour not priced again before ``detours.recheck_s``, an outcome settled by the merge that
follows, and the events that carry both estimates. A real fleet (robots, teams, event log);
the teams' explored areas are fed as the coverage updates would feed them."""

from __future__ import annotations

import pytest

from server.config import ServerConfig
from server.fleet.detours import Detours
from server.fleet.events import EventLog
from server.fleet.model import Fleet
from server.fleet.pricing import Pending, Price
from server.fleet.rates import Rates
from server.fleet.stages import Stages

S = 1_000_000_000   # ns per s
AREA, THETA = 400.0, 0.9


def config(enabled: bool = True) -> ServerConfig:
    return ServerConfig.model_validate({
        "robots": ["r1", "r2", "r3"],
        "explore": {"total_area_m2": AREA, "coverage_threshold": THETA},
        "detours": {"enabled": enabled}})


def fleet(enabled: bool = True) -> tuple[Fleet, EventLog]:
    cfg = config(enabled)
    events = EventLog()
    f = Fleet(cfg, Stages(cfg), events)
    for rid in ("r1", "r2", "r3"):
        f.add_robot(rid)
    return f, events


def grow(d: Detours, rates: dict[str, float], until_s: float = 20.0) -> None:
    """Each robot's own team exploring at its rate [m²/s] from 0 s to ``until_s``, a coverage
    update a second."""
    for t in range(int(until_s) + 1):
        for rid, rate in rates.items():
            d.observe(f"team-{rid}", [rid], t * S, rate * t)


def detour_events(events: EventLog) -> list[dict[str, float]]:
    return [dict(e.figures) for e in events.all if e.kind == "detour"]


# -- the arithmetic --------------------------------------------------------------------------

def test_rates_and_merge_saving_from_the_maps() -> None:
    rates = Rates(window_s=30.0, min_rate_m2_s=0.05, area_m2=AREA, threshold=THETA)
    for t in range(21):
        rates.observe("a", ["r1"], float(t), 1.0 * t)
        rates.observe("b", ["r2"], float(t), 2.0 * t)
    assert rates.rate("a") == pytest.approx(1.0)
    assert rates.rate("b") == pytest.approx(2.0)
    # alone: (θA − E) / R
    assert rates.finish_s("a") == pytest.approx((360.0 - 20.0) / 1.0)
    assert rates.finish_s("b") == pytest.approx((360.0 - 40.0) / 2.0)
    # merged: E_ab = 20 + 40 − 20·40/400 = 58, done in (360 − 58) / 3; apart, the first of
    # them is done in 160 s
    assert rates.merge_saving_s("a", "b") == pytest.approx(160.0 - (360.0 - 58.0) / 3.0)
    # a robot's share of a team's rate follows the rates its robots had alone
    rates.observe("a", ["r1", "r2"], 21.0, 60.0)
    assert rates.robot_rate("r2", "a") == pytest.approx(2.0 * rates.robot_rate("r1", "a"))


def test_a_price_is_taken_only_when_the_saving_is_larger() -> None:
    cheap = Price("call", ("r1",), robot_s=10.0, cost_s=4.0, gain_s=10.0, p=0.5)
    assert cheap.saving_s == pytest.approx(5.0) and cheap.worth
    dear = Price("call", ("r1",), robot_s=10.0, cost_s=5.0, gain_s=10.0, p=0.5)
    assert not dear.worth   # an equal saving does not pay for the robot's time


def test_a_call_priced_from_the_teams_maps_and_recorded_with_its_figures() -> None:
    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0})
    gain = 160.0 - (360.0 - 58.0) / 3.0
    # 3 m to the caller at 0.3 m/s and a hold of 3 s: 13 s of r1's time, which maps 13 m²
    # that the merged team (3 m²/s) would take 13/3 s to map
    assert d.call(f.robots["r1"], "r2", 3.0, 20 * S)
    ev = detour_events(events)[-1]
    assert ev["robot_s"] == pytest.approx(13.0)
    assert ev["cost_s"] == pytest.approx(13.0 / 3.0)
    assert ev["gain_s"] == pytest.approx(gain)
    assert ev["p"] == pytest.approx(0.5)
    assert ev["saving_s"] == pytest.approx(0.5 * gain)
    assert ev["taken"] == 1.0
    assert [p.kind for p in d.pending] == ["call"]


# -- declined, and not priced again too soon -------------------------------------------------

def test_a_declined_detour_is_not_priced_again_before_recheck() -> None:
    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0})
    r1 = f.robots["r1"]
    # 300 m away: 1003 s of r1's time costs the team far more than the merge could save
    assert not d.call(r1, "r2", 300.0, 20 * S)
    ev = detour_events(events)[-1]
    assert ev["taken"] == 0.0 and ev["cost_s"] > ev["saving_s"]
    assert d.pending == []
    recheck = f.cfg.detours.recheck_s
    assert d.recently_declined(r1, "call", "r2", int((20 + recheck - 0.5) * S))
    assert not d.recently_declined(r1, "call", "r3", 21 * S)     # another caller: priced
    assert not d.recently_declined(r1, "seek", "r2", 21 * S)     # another kind: priced
    assert not d.recently_declined(r1, "call", "r2", int((20 + recheck + 0.5) * S))


def test_off_every_detour_is_taken_and_still_priced() -> None:
    f, events = fleet(enabled=False)
    grow(f.detours, {"r1": 1.0, "r2": 2.0})
    assert f.detours.call(f.robots["r1"], "r2", 300.0, 20 * S)
    ev = detour_events(events)[-1]
    assert ev["taken"] == 1.0 and ev["cost_s"] > ev["saving_s"]


# -- outcomes ---------------------------------------------------------------------------------

def test_an_outcome_settled_by_the_merge_that_follows() -> None:
    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0, "r3": 1.0})
    assert d.call(f.robots["r1"], "r2", 3.0, 20 * S)
    expected = detour_events(events)[-1]["saving_s"]
    # r1's and r2's teams merge 25 s later: the merged map holds 70 m² of the 20 + 50
    d.observe("team-r3", ["r3"], 45 * S, 45.0)
    d.observe("team-r1", ["r1", "r2"], 45 * S, 70.0)
    settled = detour_events(events)[-1]
    assert set(settled) == {"id", "measured_s", "saving_s", "after_s"}
    assert settled["id"] == 1.0 and settled["saving_s"] == pytest.approx(expected)
    assert settled["after_s"] == pytest.approx(25.0)
    # apart, r1's team was done first in (360 − 20) / 1 s... merged, in (360 − 70) / 3 s
    assert settled["measured_s"] == pytest.approx(min(340.0, 160.0) - 290.0 / 3.0)
    assert d.pending == []
    # the run's own outcome now counts: one call that paid, on a prior of 0.5 over 3
    assert d.p("call") == pytest.approx((1 + 0.5 * 3) / (1 + 3))


def test_a_merge_of_other_teams_is_not_the_outcome_and_time_runs_out() -> None:
    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0, "r3": 1.0})
    assert d.call(f.robots["r1"], "r2", 3.0, 20 * S)
    d.observe("team-r2", ["r2", "r3"], 30 * S, 80.0)     # r2 merged with r3, not with r1
    assert len(d.pending) == 1
    deadline = d.pending[0].deadline_ns
    d.tick(deadline - S)
    assert len(d.pending) == 1
    d.tick(deadline + S)
    settled = detour_events(events)[-1]
    assert settled["measured_s"] == 0.0 and d.pending == []
    assert d.p("call") == pytest.approx(0.5 * 3 / (1 + 3))


def test_which_merge_settles_a_pending_detour() -> None:
    p = Pending(1, "call", "r1", "r2", 0, S, 5.0, 10.0)
    assert p.merged_by(frozenset({"r1"}), frozenset({"r2", "r3"}))
    assert p.merged_by(frozenset({"r2"}), frozenset({"r1"}))
    assert not p.merged_by(frozenset({"r1"}), frozenset({"r3"}))
    seek = Pending(2, "seek", "r1", "", 0, S, 5.0, 10.0)
    assert seek.merged_by(frozenset({"r3"}), frozenset({"r1"}))


def test_a_turning_cameras_stop_is_priced_by_the_drift_since_its_last_whole_scan() -> None:
    import math

    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0})
    r2 = f.robots["r2"]
    assert d.sweep(r2, 20 * S)                       # the first: the map's heading reference
    assert detour_events(events)[-1]["p"] == 1.0
    r2.slam.stats.sweeps += 1                        # its whole scan came
    assert not d.sweep(r2, 21 * S)                   # not driven since: nothing to correct
    assert detour_events(events)[-1]["p"] == 0.0
    r2.distance_m = 4.0
    d.sweep(r2, 30 * S)
    cfg = f.cfg.detours
    share = cfg.drift_m_per_sqrt_m * 2.0 * math.sqrt(2.0 / math.pi) / cfg.tolerance_m
    ev = detour_events(events)[-1]
    assert ev["p"] == pytest.approx(share)
    # its rate against the fleet's: r1's and r2's teams, and r3's at the least rate
    assert ev["cost_s"] == pytest.approx(cfg.sweep_s * 2.0 / (3.0 + cfg.min_rate_m2_s))


def test_the_drift_of_a_stop_counts_from_where_the_last_whole_scan_came() -> None:
    import math

    f, events = fleet()
    d = f.detours
    grow(d, {"r1": 1.0, "r2": 2.0})
    r2 = f.robots["r2"]
    r2.distance_m = 3.0
    assert d.sweep(r2, 20 * S)
    r2.slam.stats.sweeps += 1                        # its whole scan came, 3 m along
    d.tick(21 * S)
    assert detour_events(events)[-1].keys() >= {"measured_s"} and d.pending == []
    r2.distance_m = 4.0                              # a metre later, the next stop
    d.sweep(r2, 30 * S)
    cfg = f.cfg.detours
    share = cfg.drift_m_per_sqrt_m * 1.0 * math.sqrt(2.0 / math.pi) / cfg.tolerance_m
    ev = detour_events(events)[-1]
    assert ev["p"] == pytest.approx(share) and ev["taken"] == 1.0
