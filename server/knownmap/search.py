"""One unplaced team's search for its place in the known map, query after query.

A team not yet in the known map (a robot that joined at an unknown pose, or robots that met
before either was placed) has its map matched against the known map every
``query_period_s`` (``server.knownmap.placing``). Each query's clear winner, if there is one,
is a guess; a guess that wins ``confirmations`` queries in a row — the team's map growing in
between — is put to the merger's checks. Any query without a clear winner, or won by another
transform, sets every guess back to no wins: evidence that tells places apart must keep
telling them apart. A guess the merger's checks refuse is put forward again only once the
team's map has twice the keyframes it had then (more evidence: a wrong place is refused
again), and never after ``MAX_REFUSALS``. No I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import compose
from server.knownmap.placing import Placement
from server.rendezvous.mapmatch import same_transform

F64 = NDArray[np.float64]

#: placements a search keeps to show (the console's hypotheses)
SHOWN = 3
#: refusals after which a guess is never put forward again
MAX_REFUSALS = 3


@dataclass
class Guess:
    """A transform (the team's frame -> the map's) that won a query."""

    T_map_own: F64
    first_ns: int
    last_ns: int
    strength: float
    acceptance: float
    wins: int = 1                 # queries in a row it won
    status: str = "pending"       # pending, refused, placed
    reason: str = ""
    refusals: int = 0
    retry_keyframes: int = 0      # refused: put forward again once the team has this many

    def refused(self, reason: str, keyframes: int) -> None:
        self.status, self.reason = "refused", reason
        self.refusals += 1
        self.retry_keyframes = 2 * max(keyframes, 1)

    def may_retry(self, keyframes: int) -> bool:
        """A refused guess, its team's map grown enough since, is pending again."""
        if self.status == "refused" and self.refusals < MAX_REFUSALS and \
                keyframes >= self.retry_keyframes:
            self.status = "pending"
        return self.status == "pending"

    def as_dict(self) -> dict[str, Any]:
        return {"T_map_own": [float(v) for v in self.T_map_own], "first_ns": self.first_ns,
                "last_ns": self.last_ns, "strength": round(self.strength, 2),
                "acceptance": self.acceptance, "wins": self.wins, "status": self.status,
                "reason": self.reason, "refusals": self.refusals}


@dataclass
class Search:
    """The search of one team, as long as its members stay the same (a merge or split
    moves its frame: the search starts again)."""

    members: tuple[str, ...]
    next_ns: int = 0
    queries: int = 0
    guesses: list[Guess] = field(default_factory=list)
    #: the latest query's strongest placements (transform, strength, acceptance)
    shown: list[tuple[F64, float, float]] = field(default_factory=list)

    def take(self, ranked: list[Placement], winner: Placement | None, at_own: F64,
             now_ns: int) -> Guess | None:
        """One query's answer: its placements, and its clear winner if any. Returns the
        guess the winner confirms (or starts)."""
        self.queries += 1
        self.shown = [(pl.T_map_own, pl.strength, pl.acceptance) for pl in ranked[:SHOWN]]
        found = None
        if winner is not None:     # the guess it confirms: a pending one before others
            same = [g for g in self.guesses
                    if same_transform(g.T_map_own, winner.T_map_own, at_own)]
            found = min(same, key=lambda g: g.status != "pending", default=None)
        for g in self.guesses:
            if g is not found:
                g.wins = 0
        if winner is None:
            return None
        if found is None:
            found = Guess(winner.T_map_own, now_ns, now_ns, winner.strength, winner.acceptance)
            self.guesses.append(found)
            return found
        if found.status == "pending":
            found.T_map_own = winner.T_map_own
            found.strength, found.acceptance = winner.strength, winner.acceptance
        found.wins += 1
        found.last_ns = now_ns
        return found

    def hypotheses(self, pose_own: F64) -> list[dict[str, Any]]:
        """The latest placements as the console shows them: where each puts the robot at
        ``pose_own`` (its own frame), in the map's frame."""
        out = []
        for T, strength, acceptance in self.shown:
            p = compose(T, pose_own)
            out.append({"pose": [round(float(v), 3) for v in p],
                        "strength": round(strength, 1), "acceptance": acceptance})
        return out
