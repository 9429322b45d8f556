"""Loop closure's likelihood fields: one bounded cache for every robot of the process."""

from __future__ import annotations

import pickle

import numpy as np

from server.slam.config import LoopClosureConfig
from server.slam.correlative import LikelihoodField
from server.slam.field_cache import FieldCache
from server.slam.icp import IcpParams
from server.slam.loop_closure import LoopCloser, Submap


def field(seed: int, size_m: float = 4.0) -> LikelihoodField:
    pts = np.random.default_rng(seed).uniform(0.0, size_m, (200, 2))
    return LikelihoodField(pts, 0.05, sigma_m=0.05, margin_m=0.2, levels=7)


def nbytes(f: LikelihoodField) -> int:
    return sum(level.nbytes for level in f.pyramid)


def test_the_total_bound_drops_the_least_lately_used_of_any_owner() -> None:
    one = nbytes(field(0))
    cache = FieldCache(total_bytes=int(3.5 * one))
    for owner, index in [(1, 0), (2, 0), (1, 1)]:
        cache.put(owner, index, field(owner * 10 + index), 100 * one, 24)
    assert cache.get(1, 0) is not None          # (1, 0) used again: (2, 0) is the oldest now
    cache.put(3, 0, field(30), 100 * one, 24)
    assert len(cache) == 3 and cache.held_bytes <= 3.5 * one
    assert cache.get(2, 0) is None
    assert all(cache.get(o, i) is not None for o, i in [(1, 0), (1, 1), (3, 0)])


def test_an_owner_keeps_within_its_own_bounds_and_leaves_the_others_fields() -> None:
    one = nbytes(field(0))
    cache = FieldCache(total_bytes=100 * one)
    cache.put(2, 0, field(20), 100 * one, 24)
    for index in range(5):
        cache.put(1, index, field(index), int(2.5 * one), 24)
    assert [cache.get(1, i) is not None for i in range(5)] == [False, False, False, True, True]
    assert cache.get(2, 0) is not None
    for index in range(5, 8):                    # a bound by count as well
        cache.put(1, index, field(index), 100 * one, 2)
    assert [cache.get(1, i) is not None for i in range(3, 8)] == [False] * 3 + [True, True]
    # the field just made stays, even alone above every bound
    tiny = FieldCache(total_bytes=1)
    tiny.put(1, 0, field(0), 1, 1)
    assert tiny.get(1, 0) is not None and len(tiny) == 1
    assert cache.held_bytes == sum(nbytes(f) for f in (cache.get(1, 6), cache.get(1, 7),
                                                        cache.get(2, 0)) if f is not None)


def test_closers_do_not_share_fields_and_a_copy_makes_its_own() -> None:
    cfg = LoopClosureConfig()
    a, b = LoopCloser(cfg, IcpParams()), LoopCloser(cfg, IcpParams())
    rng = np.random.default_rng(1)
    for closer, shift in [(a, 0.0), (b, 3.0)]:
        pts = rng.uniform(0.0, 4.0, (300, 2)) + shift
        closer.submaps.append(Submap(0, [0], pts, np.zeros_like(pts)))
    fa, fb = a._field(0), b._field(0)
    assert fa is not fb and not np.array_equal(fa.origin, fb.origin)
    assert a._field(0) is fa                     # kept
    copy = pickle.loads(pickle.dumps(a))
    fc = copy._field(0)
    assert fc is not fa                          # made again for the copy, the same field
    assert all(np.array_equal(x, y) for x, y in zip(fc.pyramid, fa.pyramid, strict=True))
