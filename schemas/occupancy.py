"""Occupancy cell values, nav2's ``OccupancyGrid`` convention: the wire's ``MapUpdate``, the
SLAM grid, the planners, the simulator's true maps and the report all use these.

A cell holds ``UNKNOWN`` (never observed, or outside the world) or the probability that it is
occupied, in percent: ``FREE`` (0) ... ``OCCUPIED`` (100). An estimated cell is classified free
below ``FREE_BELOW``, occupied above ``OCCUPIED_ABOVE``, and observed without a verdict between
the two (inclusive).
"""

from __future__ import annotations

UNKNOWN = -1
FREE = 0
OCCUPIED = 100
#: [%] an observed cell less likely occupied than this is free
FREE_BELOW = 40
#: [%] a cell more likely occupied than this is occupied (a wall to the planners)
OCCUPIED_ABOVE = 70
