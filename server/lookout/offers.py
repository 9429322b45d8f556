"""The detours a lookout starts, offered to the arbiter to be priced before they go on.

Turning to something that moves, approaching it, and answering a call all take a robot off
its own exploration. The lookout does not judge whether that is worth the time: each time it
starts one it makes an ``Offer`` (the kind, the robot it is about, where it leads), and the
arbiter (``server.command.steering``) prices it (``server.fleet.detours``). Taken, further
starts about the same robot within the time granted go on without a new price; declined, the
lookout drops it and hears no calls about that robot (nor seeks, for ``seek``) until the time
given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Offer:
    """A detour the lookout just started."""

    kind: str            # "seek" (something that moves) or "call" (a tag sighting's)
    caller: str          # the other robot ("" when not known: a seek)
    xy: F64              # where it leads (map frame)
    started_s: float


@dataclass
class Offers:
    """The latest offer not yet priced, and the answers given (see the module)."""

    pending: Offer | None = None
    granted: dict[str, float] = field(default_factory=dict)    # caller -> until [s]
    declined: dict[str, float] = field(default_factory=dict)   # caller -> until [s]

    def make(self, kind: str, caller: str, xy: F64, now_s: float) -> None:
        """The lookout starts a detour (not offered again while one about the same robot is
        granted)."""
        if self.granted.get(caller, -math.inf) >= now_s:
            return
        self.pending = Offer(kind, caller, np.asarray(xy, dtype=np.float64).copy(), now_s)

    def grant(self, offer: Offer, until_s: float) -> None:
        self.granted[offer.caller] = until_s
        self.pending = None

    def decline(self, offer: Offer, until_s: float) -> None:
        self.declined[offer.caller] = until_s
        self.pending = None

    def refused(self, caller: str, now_s: float) -> bool:
        """Whether detours about ``caller`` were declined until after ``now_s``."""
        return self.declined.get(caller, -math.inf) > now_s
