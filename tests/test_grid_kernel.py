"""The compiled scan update of the occupancy grid (``server.slam.grid_kernel``) and loop
closure's compiled path lengths (``server.slam.loop_kernel``) give the same grid and the same
distances, bit for bit, as the numpy steps they replaced (written out here as references)."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

from server.slam.grid import _MARK_Q, _TILE_BITS, TILE, UNKNOWN_Q, GridParams, OccupancyGrid


def _slots_numpy(g: OccupancyGrid, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    iw = g._index.shape[1]
    t0x, t0y = g._index_t0.tolist()
    tile = (gy >> _TILE_BITS) - t0y
    tile *= iw
    tile += (gx >> _TILE_BITS) - t0x
    index = g._index.reshape(-1)
    slot = index[tile]
    missing = slot < 0
    if missing.any():
        new = np.unique(tile[missing])
        g._allocate(len(new))
        index[new] = np.arange(g._tiles - len(new), g._tiles)
        slot = index[tile]
    out = slot.astype(np.int64) << (2 * _TILE_BITS)
    out += (gy & (TILE - 1)) << _TILE_BITS
    out += gx & (TILE - 1)
    return out


def _insert_numpy(g: OccupancyGrid, T: np.ndarray, hits: np.ndarray,
                  misses: np.ndarray | None) -> None:
    """``insert_scan`` as numpy steps (the implementation before the compiled one)."""
    c, s = math.cos(T[2]), math.sin(T[2])
    R = np.array([[c, -s], [s, c]])
    max_ray = g.params.max_ray_m
    far = np.hypot(hits[:, 0], hits[:, 1]) > max_ray
    ends = hits[~far] @ R.T + T[:2]
    parts = [ends]
    if far.any():
        parts.append(hits[far] @ R.T + T[:2])
    if misses is not None and len(misses):
        parts.append(misses @ R.T + T[:2])
    rays = np.concatenate(parts) if len(parts) > 1 else ends
    if len(rays) == 0:
        return
    vec = rays - T[:2]
    length = np.hypot(vec[:, 0], vec[:, 1])
    scale = np.minimum(1.0, max_ray / np.maximum(length, 1e-9))
    rays = T[:2] + vec * scale[:, None]
    g.ensure_contains(np.minimum(rays.min(axis=0), T[:2]), np.maximum(rays.max(axis=0), T[:2]))
    res = g.resolution_m
    step = 0.7 * res
    lengths = length * scale
    n_samp = np.ceil(lengths / step).astype(np.int64)
    total = int(n_samp.sum())
    ray_id = np.repeat(np.arange(len(rays)), n_samp)
    first = np.cumsum(n_samp) - n_samp
    k = np.arange(total) - np.repeat(first, n_samp)
    frac = (k * step) / np.maximum(lengths[ray_id], 1e-9)
    px = T[0] + frac * (rays[ray_id, 0] - T[0])
    py = T[1] + frac * (rays[ray_id, 1] - T[1])
    gx = np.floor((px - g._anchor[0]) / res).astype(np.int64)
    gy = np.floor((py - g._anchor[1]) / res).astype(np.int64)
    free = _slots_numpy(g, gx, gy)
    hit_cells = g._lattice(ends)
    hit = _slots_numpy(g, hit_cells[:, 0], hit_cells[:, 1])
    pool = g._pool.reshape(-1)
    kept = pool[hit]
    pool[hit] = _MARK_Q
    free = free[pool[free] != _MARK_Q]
    pool[hit] = kept
    v = pool[free]
    v[v == UNKNOWN_Q] = 0
    v += g._l_miss
    pool[free] = np.maximum(v, g._l_min)
    v = pool[hit]
    v[v == UNKNOWN_Q] = 0
    v += g._l_hit
    pool[hit] = np.minimum(v, g._l_max)


def test_compiled_update_is_the_numpy_one_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    compiled = OccupancyGrid(GridParams(max_ray_m=6.0))
    reference = copy.deepcopy(compiled)
    for _ in range(40):
        T = np.array([*rng.uniform(-8, 8, 2), rng.uniform(-math.pi, math.pi)])
        n = int(rng.integers(0, 200))
        a = rng.uniform(-math.pi, math.pi, n)
        r = rng.uniform(0.1, 9.0, n)             # some beyond max_ray_m: cleared only
        hits = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        hits = np.concatenate([hits, hits[: n // 4]])   # the same cells hit twice
        misses = 4.0 * np.stack([np.cos(a[:10]), np.sin(a[:10])], axis=1)
        compiled.insert_scan(T, hits, misses)
        _insert_numpy(reference, T, hits, misses)
    assert compiled.shape == reference.shape
    assert np.array_equal(compiled.origin, reference.origin)
    assert compiled.tiles == reference.tiles
    q = compiled.quantised()
    assert np.array_equal(q, reference.quantised())
    assert (q != UNKNOWN_Q).sum() > 1000 and (q > 0).any() and ((q < 0) & (q != UNKNOWN_Q)).any()


def test_compiled_path_lengths_are_the_numpy_relaxation_bit_for_bit() -> None:
    """``loop_kernel.relax`` against the numpy loop it replaced, on a chain with shortcuts."""
    from server.slam.loop_closure import _Graph

    rng = np.random.default_rng(5)
    g = _Graph()
    for k in range(1, 300):
        g.add_edge(k - 1, k, float(rng.uniform(0.05, 0.6)))
    for _ in range(40):
        a, b = sorted(rng.integers(0, 300, 2).tolist())
        g.add_edge(a, b, float(rng.uniform(0.0, 1.0)))
    for source in (0, 17, 150, 299):
        d = np.abs(g.arc - g.arc[source])
        for _ in range(len(g.shortcuts) + 1):
            changed = False
            for a, b, w in g.shortcuts:
                for u, v in ((a, b), (b, a)):
                    via = d[u] + w
                    if via < d[v] - 1e-9:
                        np.minimum(d, via + np.abs(g.arc - g.arc[v]), out=d)
                        changed = True
            if not changed:
                break
        got = g.distances_from(source, 310)
        assert np.array_equal(got[:300], d) and np.isinf(got[300:]).all()
        assert (got[:300] < np.abs(g.arc - g.arc[source]) - 1e-6).any() or source == 0


def test_a_cell_outside_the_tiles_is_refused_not_written() -> None:
    g = OccupancyGrid(GridParams())
    g.insert_scan(np.zeros(3), np.array([[1.0, 0.0]]))
    before = g.quantised().copy()
    far = np.array([10_000], dtype=np.int64)
    with pytest.raises(IndexError, match="outside the grid"):
        g._slots_lattice(far, far)
    assert np.array_equal(g.quantised(), before)
