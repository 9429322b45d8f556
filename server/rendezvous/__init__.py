"""Rendezvous: from tag sightings to merged maps, and back when the evidence turns.

Modules (import them directly; this package imports nothing):

    desk     = SightingDesk(...)   # intake, waiting for scans, placing on keyframes
    evidence = MergeVerifier(...)  # RANSAC over a pair of teams' sightings -> MergeProposal
    merger   = Merger(...)         # verify on the maps -> commit (one graph) | refuse | defer
    surgery  = GraphSurgery(...)   # joint graphs, map-match factors, retiring sightings
    maps     = map_agreement(...), cross_matches(...)   # how two maps fit under a transform
    counters = RendezvousCounters()                      # what became of every sighting
"""
