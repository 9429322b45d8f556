"""What a team's exploration is worth in time, read off its map: how much it has explored, how
fast that grows, when it would be done alone, and what a merge of two teams saves.

Every action that takes a robot off its own exploration is priced in the fleet's time to reach
its coverage threshold (``server.fleet.detours``). The figures that price comes from are kept
here, from each team's explored area at every coverage update (``server.fleet.progress``):

1. **Explored area** E of each team [m²]: the explored cells of its planning grid.
2. **Rate** R of each team [m²/s]: E's growth over the last ``detours.rate_window_s``, since
   the team last changed (a merge's jump in E is not exploration), and never below half its
   average since then, nor below half the rates of the teams it was merged from (a robot
   crossing known ground for a while has not stopped being worth its time), nor below
   ``detours.min_rate_m2_s``. Each robot's own rate is measured while it
   explores alone; a team's rate is shared among its robots in proportion to those (a depth
   camera's robot maps a fraction of what a LIDAR's does).
3. **Time to finish alone**: T = (θ·A − E) / R, with A the area to cover and θ the coverage
   threshold (without a known area, A is taken as twice the largest team's E).
4. **A merge's worth**: merged, teams a and b know E_ab = E_a + E_b − E_a·E_b / A (their maps
   overlap as two independent draws from the building would) and finish in
   T_ab = (θ·A − E_ab) / (R_a + R_b). Apart, the fleet is done no sooner than the first of
   them, min(T_a, T_b), which the other then joins. The merge saves
   S = min(T_a, T_b) − T_ab, or nothing if that is negative.

When a merge happens, ``observe`` sees the merged team's map and gives the same saving from
what the merged map actually holds in place of the estimated overlap (``MergeSeen``): the
outcome a detour's estimate is checked against.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

#: a team's time to finish is never taken as longer than this [s] (a team that maps nothing)
LONGEST_S = 36_000.0


@dataclass
class Track:
    """A team's explored area over time, since its robots last changed."""

    robots: frozenset[str]
    samples: deque[tuple[float, float]] = field(default_factory=deque)   # (t [s], E [m²])
    first: tuple[float, float] | None = None    # the first sample, kept for the average
    base_rate: float = 0.0    # the rates of the teams it was merged from, summed [m²/s]

    @property
    def explored_m2(self) -> float:
        return self.samples[-1][1] if self.samples else 0.0


@dataclass(frozen=True)
class MergeSeen:
    """A merge, as the maps before and after it tell: what it saved the fleet."""

    t_s: float
    robots_a: frozenset[str]
    robots_b: frozenset[str]
    saving_s: float


class Rates:
    """Explored areas and rates of the fleet's teams (see the module)."""

    def __init__(self, window_s: float, min_rate_m2_s: float, area_m2: float | None,
                 threshold: float) -> None:
        self.window_s, self.min_rate = window_s, min_rate_m2_s
        self.area_m2, self.threshold = area_m2, threshold
        self.tracks: dict[str, Track] = {}
        #: each robot's rate while it explored alone [m²/s]
        self.alone: dict[str, float] = {}

    # -- observing the maps ------------------------------------------------------------------
    def observe(self, team_id: str, robots: list[str], t_s: float, explored_m2: float
                ) -> MergeSeen | None:
        """A team's explored area at ``t_s``; the merge that made the team, when this is the
        first look at its map since."""
        now = frozenset(robots)
        track = self.tracks.get(team_id)
        seen = None
        if track is None or track.robots != now:
            parts = [tr for tr in self.tracks.values() if tr.robots and tr.robots <= now]
            base = sum(self._rate(tr) for tr in parts)
            seen = self._merged(team_id, now, t_s, explored_m2)
            track = self.tracks[team_id] = Track(now, base_rate=base)
        track.samples.append((t_s, explored_m2))
        if track.first is None:
            track.first = (t_s, explored_m2)
        while len(track.samples) > 2 and track.samples[1][0] <= t_s - self.window_s:
            track.samples.popleft()
        if len(now) == 1 and t_s - track.first[0] >= min(self.window_s, 10.0):
            self.alone[next(iter(now))] = self._measured(track)
        return seen

    def _merged(self, team_id: str, now: frozenset[str], t_s: float, explored_m2: float
                ) -> MergeSeen | None:
        """The teams whose robots now make up ``team_id`` (gone from the map's teams), as a
        merge seen; their tracks are dropped."""
        parts = [(tid, tr) for tid, tr in self.tracks.items() if tr.robots and tr.robots <= now]
        for tid, _ in parts:
            del self.tracks[tid]
        if len(parts) != 2:
            return None
        (_, a), (_, b) = parts
        e_a, e_b = a.explored_m2, b.explored_m2
        r_a, r_b = self._rate(a), self._rate(b)
        saving = max(0.0, min(self._finish(e_a, r_a, e_b), self._finish(e_b, r_b, e_a))
                     - self._finish(explored_m2, r_a + r_b, explored_m2))
        return MergeSeen(t_s, a.robots, b.robots, saving)

    # -- the figures -------------------------------------------------------------------------
    def explored_m2(self, team_id: str) -> float:
        track = self.tracks.get(team_id)
        return 0.0 if track is None else track.explored_m2

    def rate(self, team_id: str) -> float:
        """The team's rate [m²/s] (see the module); the sum of its robots' own rates while
        its track is still short."""
        track = self.tracks.get(team_id)
        return self.min_rate if track is None else self._rate(track)

    def robot_rate(self, robot_id: str, team_id: str) -> float:
        """The robot's share of its team's rate, in proportion to the rates its team's
        robots had alone."""
        track = self.tracks.get(team_id)
        if track is None or len(track.robots) < 2:
            return self.rate(team_id)
        own = {r: self.alone.get(r, self.min_rate) for r in track.robots}
        return self.rate(team_id) * own.get(robot_id, self.min_rate) / sum(own.values())

    def finish_s(self, team_id: str) -> float:
        """The team's time to its threshold alone, at its rate."""
        e = self.explored_m2(team_id)
        return self._finish(e, self.rate(team_id), e)

    def merge_saving_s(self, team_a: str, team_b: str) -> float:
        """What merging the two teams now saves the fleet (S of the module)."""
        e_a, e_b = self.explored_m2(team_a), self.explored_m2(team_b)
        r_a, r_b = self.rate(team_a), self.rate(team_b)
        union = e_a + e_b - e_a * e_b / self._area(max(e_a, e_b))
        apart = min(self._finish(e_a, r_a, e_b), self._finish(e_b, r_b, e_a))
        return max(0.0, apart - self._finish(union, r_a + r_b, max(e_a, e_b)))

    # -- helpers -----------------------------------------------------------------------------
    def _area(self, largest_m2: float) -> float:
        if self.area_m2:
            return self.area_m2
        return max(2.0 * max(largest_m2, max((t.explored_m2 for t in self.tracks.values()),
                                             default=0.0)), 1.0)

    def _finish(self, explored_m2: float, rate: float, largest_m2: float) -> float:
        left = self.threshold * self._area(largest_m2) - explored_m2
        return min(LONGEST_S, max(0.0, left) / max(rate, self.min_rate))

    def _measured(self, track: Track) -> float:
        """The track's rate: growth over the window, at least half its average."""
        t1, e1 = track.samples[-1]
        t0, e0 = track.first or track.samples[0]
        tw, ew = track.samples[0]
        if t1 - t0 <= 0:
            return self.min_rate
        windowed = (e1 - ew) / (t1 - tw) if t1 > tw else 0.0
        return max(self.min_rate, windowed, 0.5 * (e1 - e0) / (t1 - t0),
                   0.5 * track.base_rate)

    def _rate(self, track: Track) -> float:
        if track.first is not None and track.samples[-1][0] - track.first[0] >= min(
                self.window_s, 10.0):
            return self._measured(track)
        return max(self.min_rate, track.base_rate,
                   sum(self.alone.get(r, self.min_rate) for r in track.robots))
