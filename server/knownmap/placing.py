"""Where a robot's own map lies in the known map: candidates, their grouping, the clear winner.

A robot that joins at an unknown pose has a small map of its own, in its own frame. Placing
it is matching that map against the known map, with the parts and rules of merging two teams
on their maps (``server.rendezvous.mapmatch``, ``submaps``):

1. **Rotations** from the two maps' wall directions (their Hough spectra), each searched
   ±``window_deg``.
2. **Candidates.** Squares of ``submap_m`` around the robot's places (its keyframes at least
   ``spacing_m`` apart) are placed on the known map at every translation at once (FFT
   correlation), refined on the fine grid and kept when their acceptance index is at least
   ``min_acceptance``; several per square, not only the best.
3. **Placements.** Candidates that imply the same transform (``mapmatch.consistent``) are one
   placement; its strength is the best score of each of its squares, summed.
4. **A clear winner** is the strongest placement when every other scores at most
   ``ratio`` of it. In a building of rooms alike (mirror-image wings) several placements fit
   about equally: none wins, and the robot is not placed until what it sees tells them apart.

The known map's layers and their transforms are made once per version of the map
(``MapTarget``). No I/O and no server state here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_dilation

from schemas.se2 import compose
from server.rendezvous.mapmatch import Candidate, Layers, MatchParams, consistent, layers
from server.rendezvous.submaps import (
    Target,
    hough_spectrum,
    match_submap,
    rotation_peaks,
    submap_centres,
)
from server.slam.grid import OccupancyGrid

F64 = NDArray[np.float64]


class MapTarget:
    """The known map as every query matches against it: layers, spectrum, FFTs."""

    def __init__(self, grid: OccupancyGrid, p: MatchParams) -> None:
        self.layers: Layers = layers(grid, p.cell_m)
        self.spectrum = hough_spectrum(self.layers.occ)
        self.target = Target(self.layers, p.submap_m, p.conflict_weight)


@dataclass(frozen=True)
class Placement:
    """Candidates that agree on one transform: the robot's frame -> the map's."""

    T_map_own: F64
    members: tuple[Candidate, ...]
    strength: float           # best score of each submap among the members, summed
    acceptance: float         # best among the members

    @property
    def submaps(self) -> int:
        return len({c.submap for c in self.members})


def candidates(target: MapTarget, own: OccupancyGrid, places_xy: F64, p: MatchParams
               ) -> list[Candidate]:
    """Step 1 and 2: the robot's squares (around its ``places_xy``, own frame) placed on the
    known map; each candidate's ``T_ab`` takes the robot's frame to the map's."""
    lay = layers(own, p.cell_m)
    # the robot's open space away from its own walls: its frame is turned against the map's,
    # and turned cells next to a wall fall on the map's wall cells as often as not
    lay.free = lay.free & ~binary_dilation(lay.occ)
    rot = rotation_peaks(target.spectrum, hough_spectrum(lay.occ), p.max_rotation_peaks)
    if not rot:
        return []
    out: list[Candidate] = []
    for k, c in enumerate(submap_centres(places_xy, lay, p)):
        out += match_submap(lay, c, target.target, rot, p, "b", k, to_ab=True)
    return out


def placements(cands: list[Candidate], p: MatchParams) -> list[Placement]:
    """Step 3: candidates grouped by the transform they imply, strongest first. A candidate
    joins the first group whose every member it is consistent with (strongest first)."""
    groups: list[list[Candidate]] = []
    for c in sorted(cands, key=lambda c: -c.score):
        for g in groups:
            if all(consistent(c, m, p) for m in g):
                g.append(c)
                break
        else:
            groups.append([c])
    out = []
    for g in groups:
        best: dict[int, float] = {}
        for c in g:
            best[c.submap] = max(best.get(c.submap, -math.inf), c.score)
        out.append(Placement(_mean([c.T_ab for c in g]), tuple(g), float(sum(best.values())),
                             max(c.acceptance for c in g)))
    return sorted(out, key=lambda pl: -pl.strength)


def clear_winner(ranked: list[Placement], ratio: float) -> Placement | None:
    """Step 4: the strongest placement, when every other scores at most ``ratio`` of it."""
    if not ranked or ranked[0].strength <= 0:
        return None
    if len(ranked) > 1 and ranked[1].strength > ratio * ranked[0].strength:
        return None
    return ranked[0]


def _mean(Ts: list[F64]) -> F64:
    th = math.atan2(sum(math.sin(T[2]) for T in Ts), sum(math.cos(T[2]) for T in Ts))
    xy = np.mean([T[:2] for T in Ts], axis=0)
    return np.array([xy[0], xy[1], th])


def robot_in_map(pl: Placement, pose_own: F64) -> F64:
    """Where a placement puts the robot (its pose ``pose_own`` in its own frame), map frame."""
    return compose(pl.T_map_own, pose_own)
