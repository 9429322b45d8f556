"""Detours, priced: no robot leaves its own exploration for a teammate unless the team gains
more time than it loses.

Every action that takes a robot off its own exploration is first priced from the maps, in the
fleet's time to reach its coverage threshold (figures from ``server.fleet.rates``), and taken
only when the expected saving is larger than the cost (``detours.enabled``; off, every detour
is taken, as before):

- ``seek``: turning to, or driving to, something the LIDAR sees moving. Its time: the way
  there and the hold. It may bring a merge with some other team (the mean over them).
- ``call``: answering a tag sighting by another team's robot: the way to the caller and the
  hold, for a merge with the caller's team.
- ``meeting``: both robots of a meeting planned on the maps: each one's path and the hold,
  for a merge of the two teams.
- ``keep_clear``: holding still while a teammate passes through a narrow place: the hold,
  for both robots' time lost tangled there.
- ``sweep``: a turning camera's stop for a whole scan: one turn of the tower, for the
  robot's map kept from drift.

1. **Cost** ``cost_s = robot_s · r / R``: what the robot would have mapped meanwhile (r its
   rate), in the time the team it works for (R, the two teams merged for a merge's detour)
   takes to map that much.
2. **Saving** ``saving_s = p · gain_s``: ``p`` is how often such detours have paid so far in
   this run, starting from ``detours.<kind>_p`` (weighted as ``detours.prior_weight`` tries).
3. Taken when ``saving_s > cost_s``. A ``detour`` event records the decision and its figures;
   a detour declined is not priced again for ``detours.recheck_s``.
4. **Outcome**: a merge of the robot's team with the other one (any other, for ``seek``)
   within ``robot_s + detours.outcome_window_s`` is the detour's outcome, its measured saving
   that merge's as the merged map tells it; no merge in time measures 0. A sweep's outcome is
   its whole scan's correction, a hold's whether the teammate got through. A second ``detour``
   event gives it (figure ``measured_s``) beside the estimate.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from server.config import ServerConfig
from server.fleet.events import EventLog
from server.fleet.pricing import Pending, Price, merge_price
from server.fleet.rates import Rates

if TYPE_CHECKING:
    from server.fleet.model import Fleet, RobotContext

log = logging.getLogger(__name__)

KINDS = ("seek", "call", "meeting", "keep_clear", "sweep")


@dataclass
class Tally:
    """How the decisions of one kind came out so far in this run."""

    tries: int = 0
    paid: int = 0


class Detours:
    """Prices, decisions and outcomes of the fleet's detours (see the module)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, events: EventLog) -> None:
        self.cfg, self.fleet, self.events = cfg, fleet, events
        d, e = cfg.detours, cfg.explore
        self.rates = Rates(d.rate_window_s, d.min_rate_m2_s, e.total_area_m2,
                           e.coverage_threshold)
        self.tally = {k: Tally() for k in KINDS}
        self.pending: list[Pending] = []
        self.decisions = 0
        #: (robot, kind, about whom) -> when a declined detour may be priced again [s]
        self.declined: dict[tuple[str, str, str], float] = {}
        #: per narrow robot: its whole scans matched, and its distance driven, at the last one
        self.whole_at: dict[str, tuple[int, float]] = {}

    # -- the figures -------------------------------------------------------------------------
    def observe(self, team_id: str, robots: list[str], stamp_ns: int, explored_m2: float) -> None:
        """A team's map at a coverage update; a merge seen there settles the detours whose
        outcome it is."""
        seen = self.rates.observe(team_id, robots, stamp_ns * 1e-9, explored_m2)
        if seen is None:
            return
        for p in list(self.pending):
            if p.kind in ("seek", "call", "meeting") and p.merged_by(seen.robots_a,
                                                                     seen.robots_b):
                self._settle(p, seen.saving_s, stamp_ns,
                             f"merged {seen.t_s - p.stamp_ns * 1e-9:.0f} s later")

    def p(self, kind: str) -> float:
        """The chance such a detour pays, from this run's outcomes and the prior."""
        t, w = self.tally[kind], self.cfg.detours.prior_weight
        prior = getattr(self.cfg.detours, f"{kind}_p")
        return (t.paid + prior * w) / (t.tries + w)

    # -- the decisions -----------------------------------------------------------------------
    def seek(self, r: RobotContext, distance_m: float, stamp_ns: int) -> bool:
        """Whether ``r`` should turn to or approach something that moves ``distance_m`` away:
        the merge with another team it may bring, their mean."""
        others = [tid for tid in self.fleet.teams if tid != r.team_id
                  and not self.fleet.seeking_paused(r.team_id, tid, stamp_ns)]
        robot_s = self._way_s(distance_m)
        if not others:
            return self._decide(Price("seek", (r.robot_id,), robot_s, robot_s, 0.0, 0.0),
                                r, "", stamp_ns)
        prices = [merge_price("seek", self.rates, [(r, robot_s)], r.team_id, tid,
                              self.p("seek")) for tid in others]
        mean = Price("seek", (r.robot_id,), robot_s,
                     sum(x.cost_s for x in prices) / len(prices),
                     sum(x.gain_s for x in prices) / len(prices), self.p("seek"))
        return self._decide(mean, r, "", stamp_ns)

    def call(self, r: RobotContext, caller: str, distance_m: float, stamp_ns: int) -> bool:
        """Whether ``r`` should answer a call by ``caller`` (another team's robot that read
        its tag, or whose tag it read) ``distance_m`` away."""
        o = self.fleet.robots.get(caller)
        robot_s = self._way_s(distance_m)
        if o is None or o.team_id == r.team_id:
            return self._decide(Price("call", (r.robot_id,), robot_s, robot_s, 0.0, 0.0), r,
                                caller, stamp_ns)
        price = merge_price("call", self.rates, [(r, robot_s)], r.team_id, o.team_id,
                            self.p("call"))
        return self._decide(price, r, caller, stamp_ns)

    def meeting(self, ra: RobotContext, rb: RobotContext, path_a_m: float, path_b_m: float,
                stamp_ns: int, transforms: int = 1) -> bool:
        """Whether two robots of two teams should go to a meeting the maps suggest, on one of
        ``transforms`` the two teams' maps fit under now (not refuted): at most one of them
        is right, so they share the chance a meeting pays (in a floor of offices alike the
        maps fit under several)."""
        price = merge_price("meeting", self.rates,
                            [(ra, self._way_s(path_a_m, 0.0)), (rb, self._way_s(path_b_m, 0.0))],
                            ra.team_id, rb.team_id, self.p("meeting") / max(1, transforms))
        return self._decide(price, ra, rb.robot_id, stamp_ns)

    def keep_clear(self, r: RobotContext, other: RobotContext, hold_s: float, tangle_p: float,
                   stamp_ns: int) -> bool:
        """Whether ``r`` should hold still ``hold_s`` while its teammate ``other`` passes a
        narrow place they would otherwise meet in with chance ``tangle_p``: a tangle costs
        both robots ``detours.tangle_s``."""
        rates, team = self.rates, r.team_id
        own, theirs = rates.robot_rate(r.robot_id, team), rates.robot_rate(other.robot_id, team)
        team_rate = rates.rate(team)
        price = Price("keep_clear", (r.robot_id,), hold_s, hold_s * own / team_rate,
                      self.cfg.detours.tangle_s * (own + theirs) / team_rate, tangle_p)
        return self._decide(price, r, other.robot_id, stamp_ns,
                            other.nav.stats.recoveries)

    def sweep(self, r: RobotContext, stamp_ns: int) -> bool:
        """Whether ``r``, whose camera turns on a tower, should stand still for a whole scan
        now. What is at stake is the robot's map: its share of its team's area, and the
        merge with another team that a map fit to merge makes possible. Its drift since its
        last whole scan (``detours.drift_m_per_sqrt_m`` per √m driven) spoils the share of
        that worth which the drift is expected to reach of ``detours.tolerance_m``; the
        first whole scan, which gives the map its heading reference, all of it. On a wide
        sensor's map of the place (a LIDAR teammate's) as much is at stake: the narrow views
        leave the pose free along a corridor's walls, and the robot drifts there all the same
        (measured: a depth robot whose stops were all declined there drifted to 0.26 m)."""
        d, rates = self.cfg.detours, self.rates
        first = r.robot_id not in self.whole_at
        since = self._since_whole_m(r)
        own = rates.robot_rate(r.robot_id, r.team_id)
        fleet_rate = sum(rates.rate(tid) for tid in self.fleet.teams)
        value_s = rates.explored_m2(r.team_id) * own / rates.rate(r.team_id) / fleet_rate + max(
            (rates.merge_saving_s(r.team_id, tid) for tid in self.fleet.teams
             if tid != r.team_id), default=0.0)
        sigma = d.drift_m_per_sqrt_m * math.sqrt(since)
        share = 1.0 if first else min(1.0, sigma * math.sqrt(2.0 / math.pi) / d.tolerance_m)
        price = Price("sweep", (r.robot_id,), d.sweep_s, d.sweep_s * own / fleet_rate,
                      value_s, share)
        return self._decide(price, r, "", stamp_ns, r.slam.stats.sweeps)

    def _since_whole_m(self, r: RobotContext) -> float:
        """How far the robot drove since its last whole scan (or since it was last on a wide
        sensor's map)."""
        count, at = self.whole_at.get(r.robot_id, (-1, 0.0))
        if r.slam.stats.sweeps != count:
            count, at = r.slam.stats.sweeps, r.distance_m
            self.whole_at[r.robot_id] = (count, at)
        return max(0.0, r.distance_m - at)

    def recently_declined(self, r: RobotContext, kind: str, about: str, stamp_ns: int) -> bool:
        """A detour of this kind, for this robot and about ``about``, was declined lately:
        not priced again yet."""
        return stamp_ns * 1e-9 < self.declined.get((r.robot_id, kind, about), -math.inf)

    # -- deciding and settling ---------------------------------------------------------------
    def _way_s(self, distance_m: float, hold: float | None = None) -> float:
        d = self.cfg.detours
        return max(0.0, distance_m) / self.cfg.control.v_mps + (d.hold_s if hold is None
                                                                 else hold)

    def _decide(self, price: Price, r: RobotContext, about: str, stamp_ns: int,
                count: int = 0) -> bool:
        """Record the decision (an event) and expect its outcome; True: taken."""
        d = self.cfg.detours
        taken = price.worth or not d.enabled
        self.decisions += 1
        ident = self.decisions
        verdict = "taken" if taken else "declined"
        whom = f" ({about})" if about else ""
        self.events.emit(
            "detour", list(price.robots), r.team_id,
            f"{price.kind}{whom}: {price.robot_s:.1f} s of the robot's time costs the team "
            f"{price.cost_s:.1f} s, saves {price.saving_s:.1f} s expected "
            f"(p {price.p:.2f} of {price.gain_s:.1f} s): {verdict}", stamp_ns,
            figures={"id": float(ident), "robot_s": price.robot_s, "cost_s": price.cost_s,
                     "saving_s": price.saving_s, "gain_s": price.gain_s, "p": price.p,
                     "taken": float(taken)})
        if taken:
            self.pending.append(Pending(ident, price.kind, r.robot_id, about, stamp_ns,
                                        stamp_ns + int((price.robot_s + d.outcome_window_s)
                                                       * 1e9), price.saving_s, price.gain_s,
                                        count))
        else:
            self.declined[(r.robot_id, price.kind, about)] = stamp_ns * 1e-9 + d.recheck_s
        log.debug("detour %d %s by %s%s: %s", ident, price.kind, r.robot_id, whom, verdict)
        return taken

    def tick(self, stamp_ns: int) -> None:
        """Sweeps whose whole scan came, holds whose teammate got through (or got stuck);
        detours whose time is up without their outcome: measured 0."""
        tol = self.cfg.detours.tolerance_m
        for p in list(self.pending):
            r = self.fleet.robots.get(p.robot_id)
            if r is not None and p.kind == "sweep" and r.slam.stats.sweeps > p.count:
                # the drift of the next stop's price counts from here, where the scan came
                self.whole_at[p.robot_id] = (r.slam.stats.sweeps, r.distance_m)
                shift = r.slam.stats.sweep_shift_m
                self._settle(p, p.gain_s * min(1.0, shift / tol), stamp_ns,
                             f"its whole scan moved it {100 * shift:.1f} cm")
            elif r is not None and p.kind == "keep_clear" and p.about in self.fleet.robots:
                o = self.fleet.robots[p.about]
                if o.nav.stats.recoveries > p.count:
                    self._settle(p, 0.0, stamp_ns, f"{o.robot_id} got stuck all the same")
                elif float(np.hypot(*(o.pose[:2] - r.pose[:2]))) > 2.0:
                    self._settle(p, p.gain_s, stamp_ns, f"{o.robot_id} got through")
            elif stamp_ns > p.deadline_ns:
                self._settle(p, 0.0, stamp_ns, "no outcome in time")

    def _settle(self, p: Pending, measured_s: float, stamp_ns: int, why: str) -> None:
        self.pending.remove(p)
        tally = self.tally[p.kind]
        tally.tries += 1
        tally.paid += measured_s > 0
        self.events.emit(
            "detour", [p.robot_id], self.fleet.robots[p.robot_id].team_id
            if p.robot_id in self.fleet.robots else None,
            f"{p.kind} {p.ident} by {p.robot_id}: measured {measured_s:.1f} s against "
            f"{p.saving_s:.1f} s expected ({why})", stamp_ns,
            figures={"id": float(p.ident), "measured_s": measured_s,
                     "saving_s": p.saving_s, "after_s": (stamp_ns - p.stamp_ns) * 1e-9})
