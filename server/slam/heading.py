"""Square walls hold the heading: most buildings' walls run along two perpendicular directions.
Where they do, a keyframe that sees walls knows its heading modulo 90° relative to any earlier
keyframe that saw walls, however far the robot has driven since: its heading drift can be taken
out without coming back to a place already mapped.

A keyframe's wall direction is the fourfold circular mean of its normals' angles (a normal at
α, α + 90°, α + 180° or α + 270° counts the same): ``m = mean(exp(4iα))``, the direction
``arg(m) / 4`` and its alignment ``|m|`` (1: every normal on one square grid; 0: no preferred
direction). Two keyframes whose alignment is high must differ in heading by the difference of
their wall directions, modulo 90°.

The rule is checked before it is used. A building whose walls are not square (or a robot whose
keyframes see no long walls) gives differences spread over ±45°; a square one gives
differences within a few degrees of the estimate. Only after ``min_checked`` keyframes, of
which ``min_agreement`` agree within ``agree_deg``, does the rule add factors, and then only
for keyframes that agree within ``max_correction_deg``: a wall off the square grid says
nothing. Each keyframe is tied to several earlier ones (the first and others spread over the
run); tied to one alone, that one view's error would turn every later keyframe by as much.

A robot whose camera turns gives its first keyframe a better wall direction than any narrow
view: the whole scan it takes standing where it started (``server.slam.sweep``). That keyframe
is then the ``reference``: every tie includes it, with its full σ, where the walls agree with
it within ``agree_deg``. Tied only to each other, the keyframes' common heading would turn with
the average drift of the odometry.

A tie constrains the relative heading alone (so it holds in any frame, and across a merge),
under a Huber kernel.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from schemas.se2 import wrap_angle

F64 = NDArray[np.float64]
QUARTER = 0.5 * math.pi


def wall_direction(normals: F64, min_points: int) -> tuple[float, float] | None:
    """(direction modulo 90° [rad] in the normals' frame, alignment in [0, 1]) of unit
    ``normals`` (N, 2); None with fewer than ``min_points`` finite ones."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    n = n[np.isfinite(n[:, 0]) & np.isfinite(n[:, 1])]
    if len(n) < min_points:
        return None
    a = np.arctan2(n[:, 1], n[:, 0])
    m = complex(np.exp(4j * a).mean())
    return math.atan2(m.imag, m.real) / 4.0, abs(m)


def wrap_quarter(a: float) -> float:
    """``a`` wrapped to [−45°, 45°)."""
    return (a + 0.25 * math.pi) % QUARTER - 0.25 * math.pi


@dataclass
class SquareWalls:
    """One robot's keyframes that saw square walls (index, wall direction) and its record of
    how often they agreed with the rule."""

    min_points: int = 20
    min_alignment: float = 0.85
    agree_deg: float = 3.0
    max_correction_deg: float = 8.0
    min_checked: int = 10
    min_agreement: float = 0.7
    partners: int = 4
    aligned: list[tuple[int, float]] = field(default_factory=list)
    checked: int = 0
    agreed: int = 0
    #: a keyframe whose wall direction is known better than any other's (a whole scan's,
    #: taken where the robot started, before it moved): every tie then includes it
    reference: tuple[int, float] | None = None

    @property
    def holds(self) -> bool:
        """Enough keyframes agreed with the rule for it to be used."""
        return self.checked >= self.min_checked and self.agreed >= self.min_agreement * self.checked

    def observe(self, k: int, normals: F64, relative_heading: Callable[[int], float]
                ) -> list[tuple[int, float]]:
        """Keyframe ``k`` with ``normals`` (its own frame); ``relative_heading(j)`` is its
        estimated heading relative to keyframe j's. Returns the keyframes j to tie it to and
        the relative heading the walls say for each: none while the rule is being checked, or
        when the keyframe shows no square walls."""
        found = wall_direction(normals, self.min_points)
        if found is None or found[1] < self.min_alignment:
            return []
        phi = found[0]
        ties: list[tuple[int, float]] = []
        if self.aligned and not self.holds:
            j, phi_j = self.reference or self.aligned[0]
            self.checked += 1
            if abs(self._correction(phi_j, phi, relative_heading(j))) <= math.radians(
                    self.agree_deg):
                self.agreed += 1
        elif self.holds:
            partners = self._partners()
            if self.reference is not None:
                partners = [self.reference] + [p for p in partners if p[0] != self.reference[0]]
            for j, phi_j in partners:
                rel = relative_heading(j)
                c = self._correction(phi_j, phi, rel)
                # the reference's tie holds hard: only where the walls agree with it
                limit = self.agree_deg if self.reference and j == self.reference[0] else \
                    self.max_correction_deg
                if abs(c) <= math.radians(limit):
                    ties.append((j, wrap_angle(rel + c)))
        self.aligned.append((k, phi))
        return ties

    @staticmethod
    def _correction(phi_j: float, phi_k: float, rel: float) -> float:
        # θ_j + φ_j ≡ θ_k + φ_k (mod 90°): θ_k − θ_j ≡ φ_j − φ_k
        return wrap_quarter(phi_j - phi_k - rel)

    def _partners(self) -> list[tuple[int, float]]:
        """The first keyframe that saw square walls and others spread evenly over the rest:
        ties to many, each with its own view's error, rather than to one."""
        n = len(self.aligned)
        picks = sorted({round(i * (n - 1) / max(self.partners - 1, 1))
                        for i in range(min(self.partners, n))})
        return [self.aligned[i] for i in picks]
