"""Progress of the exploration: each team's coverage, when a team is done, and the λ schedule.

Every ``map_period_s`` (of the time the caller runs on) each team's grid is built afresh; its
explored area over the area to cover is the team's coverage. A team finishes when that reaches
the threshold, or when all its live robots found no reachable frontier. The explorers' λ
(how much a target's information counts against its path cost) follows the fleet: while a
robot that is alive is outside a team, robots range out to meet it.
"""

from __future__ import annotations

from collections.abc import Callable

from server.config import ServerConfig
from server.exploration import explored_area_m2
from server.exploration.navigator import NavMode
from server.fleet.events import EventLog
from server.fleet.model import Fleet, Team


class Progress:
    """Coverage, termination and λ of the fleet's teams (one thread)."""

    def __init__(self, cfg: ServerConfig, fleet: Fleet, events: EventLog) -> None:
        self.cfg, self.fleet, self.events = cfg, fleet, events
        #: per team: when its next update is due
        self.next_update_ns: dict[str, int] = {}
        #: when the newest team grid in ``fleet.latest_grids`` was made
        self.map_stamp_ns = 0
        #: teams whose grid was made again since ``changed_teams`` was last asked
        self._changed: set[str] = set()
        #: a team not to finish yet whatever its coverage (a known map's team on its pass
        #: over the map: ``server.knownmap``)
        self.hold: Callable[[Team], bool] | None = None

    def tick(self, stamp_ns: int, team_id: str) -> None:
        """``update`` the team when ``map_period_s`` has passed since its last one (each team
        on its own robots' scans, so the work spreads over the period however many teams)."""
        if stamp_ns < self.next_update_ns.get(team_id, 0):
            return
        self.next_update_ns[team_id] = stamp_ns + int(self.cfg.map_period_s * 1e9)
        self.update(stamp_ns, team_id)

    def changed_teams(self) -> set[str]:
        """The teams with a new grid since the last call."""
        changed, self._changed = self._changed, set()
        return changed

    def update(self, stamp_ns: int, team_id: str | None = None) -> None:
        """Coverage of every team (or of ``team_id``) from a fresh grid; finish the teams
        that are done."""
        self.map_stamp_ns = stamp_ns
        total = self.cfg.explore.total_area_m2
        fleet = self.fleet
        for team in list(fleet.teams.values()):
            if team_id is not None and team.team_id != team_id:
                continue
            self._changed.add(team.team_id)
            grid = fleet.latest_grids[team.team_id] = fleet.planning_grid(team.team_id)
            team.explored_m2 = explored_area_m2(grid)
            team.coverage = team.explored_m2 / total if total else 0.0
            team.history.append((stamp_ns, team.coverage))
            fleet.detours.observe(team.team_id, team.robot_ids, stamp_ns, team.explored_m2)
            if team.finished or (self.hold is not None and self.hold(team)):
                pass
            elif total and team.coverage >= self.cfg.explore.coverage_threshold:
                self.finish_team(team, stamp_ns, f"coverage {team.coverage:.3f} reached")
            elif (alive := [
                    rid for rid in team.robot_ids if fleet.robots[rid].alive]) and all(
                    fleet.robots[rid].nav.mode == NavMode.DONE for rid in alive):
                # (a robot that vanished does not hold its team back; one that comes back to
                # a finished team stops too)
                self.finish_team(team, stamp_ns, "no reachable frontier left")
        self.set_lambda()

    def finish_team(self, team: Team, stamp_ns: int, why: str) -> None:
        team.finished, team.finished_stamp_ns = True, stamp_ns
        for rid in team.robot_ids:
            self.fleet.robots[rid].nav.finish(why)
        self.events.emit("terminated", team.robot_ids, team.team_id, f"{team.team_id}: {why}",
                         stamp_ns)

    def set_lambda(self) -> None:
        """λ of every robot's explorer: ``seek_lam`` while a robot that is alive is outside its
        team (the others are somewhere away from this robot's start; ranging out meets them
        sooner), ``lam`` once the team holds every robot."""
        e = self.cfg.explore
        robots = self.fleet.robots.values()
        alive_teams = {r.team_id for r in robots if r.alive}
        for r in robots:
            r.nav.set_lam(e.seek_lam if e.seek_lam is not None and alive_teams - {r.team_id}
                          else e.lam)
