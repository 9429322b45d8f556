"""What became of the tag sightings and merge proposals the server received."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass
class RendezvousCounters:
    sightings: int = 0          # tag detections received
    used: int = 0               # placed on both robots' keyframes
    unknown_robot: int = 0      # of a robot never heard of (dropped after ``max_pending_s``)
    own_tag: int = 0            # a robot's own tag ("self" in the outputs)
    bad: int = 0                # refused: a NaN, a non-positive σ
    expired: int = 0            # no scans around its time
    within_team: int = 0        # between teammates
    refined: int = 0            # ... added to the team's graph
    contradicting: int = 0      # ... disagreeing with it
    merges: int = 0
    merges_rejected: int = 0
    merges_undone: int = 0
    map_matches: int = 0        # factors from scan-to-map matches between robots
    too_far: int = 0            # beyond the usable range
    contradictions_overruled: int = 0   # the maps still matched: the merge was kept
    merges_deferred: int = 0    # far sightings waiting for a map match
    misread: int = 0            # placed a robot on a teammate: a misread tag
    sightings_retired: int = 0  # taken out of the graph once the maps tie the pair
    map_queries: int = 0        # pairs of teams whose maps were matched
    map_hypotheses: int = 0     # distinct transforms the maps suggested
    map_merges: int = 0         # merges on the maps alone
    meetings: int = 0           # planned to settle a transform the maps left open
    meetings_refuted: int = 0   # ... whose robots did not meet
    calls_paused: int = 0       # tag calls not passed on: the two teams' maps keep refusing a merge
    calls_misread: int = 0      # ... nor where the observer's teammate stands: a misread tag
    one_place_proposals: int = 0   # sightings from one place turned by the square walls
    short_path_proposals: int = 0  # ... and from a short path, turned so
    map_refuted_by_view: int = 0   # transforms refuted: a robot saw open floor where one put
    #                                a robot of the other team (``liveview``)

    def as_dict(self) -> dict[str, int]:
        """The counters by their names in the run's outputs."""
        out = dataclasses.asdict(self)
        return {("self" if k == "own_tag" else k): v for k, v in out.items()}
