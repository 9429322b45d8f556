"""A detour's price and the record of one waiting for its outcome (``server.fleet.detours``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from server.fleet.rates import Rates

if TYPE_CHECKING:
    from server.fleet.model import RobotContext


@dataclass(frozen=True)
class Price:
    """What a detour costs and may save, in the fleet's time to its threshold [s]."""

    kind: str
    robots: tuple[str, ...]    # the robots that leave their own exploration
    robot_s: float             # their time it takes (the longest of them)
    cost_s: float              # the team's time it costs
    gain_s: float              # the team's time it saves if it works
    p: float                   # the chance it works

    @property
    def saving_s(self) -> float:
        """The saving expected: ``p · gain_s``."""
        return self.p * self.gain_s

    @property
    def worth(self) -> bool:
        return self.saving_s > self.cost_s


@dataclass(frozen=True)
class Pending:
    """A detour taken, waiting for its outcome."""

    ident: int
    kind: str
    robot_id: str
    about: str                 # the other robot (a call's caller, a meeting's other robot)
    stamp_ns: int
    deadline_ns: int
    saving_s: float            # as estimated
    gain_s: float
    #: a sweep's: the robot's whole scans matched when it was taken; a hold's: the
    #: teammate's recoveries then
    count: int = 0

    def merged_by(self, robots_a: frozenset[str], robots_b: frozenset[str]) -> bool:
        """Whether a merge of these two sides is this detour's outcome: the robot on one
        side, and the robot it was about on the other (any robot, when about none)."""
        for mine, theirs in ((robots_a, robots_b), (robots_b, robots_a)):
            if self.robot_id in mine and (not self.about or self.about in theirs):
                return True
        return False


def merge_price(kind: str, rates: Rates, detouring: Sequence[tuple[RobotContext, float]],
                team_a: str, team_b: str, p: float) -> Price:
    """A detour that may merge ``team_a`` and ``team_b``: the robots' time (each robot and
    how long it is away) costs the merged team what they would have mapped meanwhile."""
    merged_rate = rates.rate(team_a) + rates.rate(team_b)
    cost = sum(s * rates.robot_rate(r.robot_id, r.team_id) for r, s in detouring) / merged_rate
    return Price(kind, tuple(r.robot_id for r, _ in detouring),
                 max(s for _, s in detouring), cost, rates.merge_saving_s(team_a, team_b), p)
