"""Map matching between teams (server.rendezvous.mapmatch) on maps built from the packaged
large house: scans ray-cast at poses inside a region, inserted into a real occupancy grid in
each robot's own frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import sim
from bench.support.scanned import box_pairs, scanned_map
from schemas.se2 import compose, inverse
from server.rendezvous.mapmatch import Candidate, MatchParams, best_hypothesis, transform_error
from server.rendezvous.submaps import hough_spectrum, match_pair, rotation_peaks
from server.slam.grid import OccupancyGrid
from sim.loader import load_world
from sim.raycast import RayCaster

WORLD = Path(sim.__file__).parent / "worlds" / "large_house.world"


@pytest.fixture(scope="module")
def caster() -> RayCaster:
    w = load_world(WORLD)
    return RayCaster(w.segments, w.circles)


def region_map(caster: RayCaster, lo: tuple[float, float], hi: tuple[float, float],
               start: np.ndarray, seed: int) -> tuple[OccupancyGrid, np.ndarray]:
    return scanned_map(caster, lo, hi, start, seed)


S_A = np.array([-20.0, -20.0, 0.0])
S_B = np.array([-8.0, -12.0, 2.2])      # turned by a non-right angle


def test_overlapping_maps_merge_under_the_true_transform(caster: RayCaster) -> None:
    ga, ka = region_map(caster, (-24, -24), (-6, -6), S_A, 1)
    gb, kb = region_map(caster, (-14, -24), (4, -6), S_B, 2)
    p = MatchParams()
    res = match_pair(ga, gb, ka, kb, p)
    T_true = compose(inverse(S_A), S_B)
    assert res.best is not None
    et, er = transform_error(res.best.T_ab, T_true)
    assert et < 0.3 and math.degrees(er) < 1.0, (et, math.degrees(er))
    assert res.best.accepted(p), res.best
    assert min(res.best.side_support("a"), res.best.side_support("b")) >= 2
    # every accepted member is itself close to the truth
    for c in res.best.members:
        assert transform_error(c.T_ab, T_true)[0] < 0.6


def test_maps_that_do_not_overlap_are_not_merged(caster: RayCaster) -> None:
    ga, ka = region_map(caster, (-24, -24), (-6, -6), S_A, 3)
    gb, kb = region_map(caster, (6, 6), (24, 24), np.array([10.0, 10.0, 1.0]), 4)
    p = MatchParams()
    res = match_pair(ga, gb, ka, kb, p)
    assert res.submaps >= 6      # there was plenty to match
    assert res.best is None or not res.best.accepted(p)


def test_rotation_peaks_find_the_turn_between_two_maps(caster: RayCaster) -> None:
    ga, _ = region_map(caster, (-24, -24), (-6, -6), S_A, 5)
    gb, _ = region_map(caster, (-24, -24), (-6, -6), S_B, 6)
    peaks = rotation_peaks(hough_spectrum(ga.occupied_mask()), hough_spectrum(gb.occupied_mask()))
    true = S_B[2] - S_A[2]
    # the true turn is within 1.5° of one of the peaks (walls are 90° apart: four peaks)
    off = min(abs(math.remainder(true - q, 2 * math.pi)) for q in peaks)
    assert math.degrees(off) < 1.5, [round(math.degrees(q), 1) for q in peaks]
    assert len(peaks) == 4


def _cand(side: str, k: int, T: np.ndarray, centre: tuple[float, float]) -> Candidate:
    return Candidate(np.asarray(T, dtype=float), side, k, np.asarray(centre, dtype=float), 100.0,
                     100, 0, 0.99, 1000)


def test_consistency_needs_both_maps_and_dominance() -> None:
    p = MatchParams()
    T1, T2 = np.array([3.0, 1.0, 0.5]), np.array([-7.0, 4.0, 0.5 + math.pi / 2])
    good = [_cand("a", 0, T1, (0, 0)), _cand("a", 1, T1, (8, 0)), _cand("b", 0, T1, (0, 8))]
    # three places agreeing, but only one of them cut from b's map: not accepted
    h = best_hypothesis(good, p)
    assert h is not None and h.support == 3 and not h.accepted(p)
    # a second b submap agreeing: accepted
    h = best_hypothesis([*good, _cand("b", 1, T1 + np.array([0.1, -0.1, 0.005]), (8, 8))], p)
    assert h is not None and h.accepted(p) and h.rival_support == 0
    # ... unless a rival transform is about as well supported
    rivals = [_cand(s, k + 5, T2, (20 + 8 * k, 20 + 8 * (s == "b"))) for s in "ab"
              for k in range(2)]
    h = best_hypothesis([*good, _cand("b", 1, T1, (8, 8)), *rivals], p)
    assert h is not None and h.rival_support == 4 and not h.accepted(p)
    # one submap's candidates never support each other
    same = [_cand("a", 0, T1 + np.array([0.05 * i, 0, 0]), (0, 0)) for i in range(4)]
    h = best_hypothesis(same, p)
    assert h is not None and h.support == 1


AMBIGUOUS = Path(sim.__file__).parent / "worlds" / "ambiguous_wings.world"


@pytest.mark.parametrize("k", [5, 9])
def test_look_alike_maps_of_a_self_similar_building_are_not_merged(k: int) -> None:
    """Boxes apart in the building of mirror-image wings and repeated corridors: their maps
    fit each other at many places under a wrong transform (before places had to be distinct,
    these two pairs were accepted, 10 m and 22 m off)."""
    w = load_world(AMBIGUOUS)
    caster = RayCaster(w.segments, w.circles)
    lo, hi = w.segments[:, :2].min(axis=0), w.segments[:, :2].max(axis=0)
    ca, cb, Sa, Sb = box_pairs(lo, hi, 12.0, 12, 0)[k]
    ga, ka = scanned_map(caster, tuple(ca - 6.0), tuple(ca + 6.0), Sa, 2 * k)
    gb, kb = scanned_map(caster, tuple(cb - 6.0), tuple(cb + 6.0), Sb, 2 * k + 1)
    p = MatchParams()
    res = match_pair(ga, gb, ka, kb, p)
    assert res.best is not None and res.best.support >= p.min_support   # it is tempting
    assert transform_error(res.best.T_ab, compose(inverse(Sa), Sb))[0] > 5.0
    assert not res.best.accepted(p), res.best
