"""The compiled map-analysis kernels give what the scipy/numpy code they replace gives, to
the bit: distances and nearest cells (ties included), pockets, frontier clusters, dilations
and the skeleton's ridge."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from skimage.morphology import skeletonize

from server.exploration.frontiers import cluster_frontiers, dilate
from server.exploration.skeleton import voronoi_skeleton
from server.exploration.skeleton_kernel import REMOVAL, thin
from server.planning.edt_kernel import edt_with_indices
from server.planning.grid import EIGHT_CONNECTED, small_components


def _masks(seed: int, n: int, p_range: tuple[float, float]) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        if k % 3 == 0:   # blobs and corridors: many equally near cells
            m = ~ndimage.binary_dilation(rng.random((h, w)) < 0.05,
                                         iterations=int(rng.integers(1, 4)))
        else:
            m = rng.random((h, w)) < rng.uniform(*p_range)
        out.append(m)
    return out


def test_edt_is_scipys_with_its_ties() -> None:
    checked = 0
    for m in _masks(1, 400, (0.3, 0.999)):
        if m.all():
            continue
        d0, i0 = ndimage.distance_transform_edt(m, return_indices=True)
        d1, i1 = edt_with_indices(m)
        np.testing.assert_array_equal(d1, d0)
        np.testing.assert_array_equal(i1, i0)
        checked += 1
    assert checked > 300
    with pytest.raises(ValueError, match="cell outside"):
        edt_with_indices(np.ones((3, 3), bool))


def _small_by_labels(mask: np.ndarray, max_cells: int) -> np.ndarray:
    if max_cells <= 0 or not mask.any():
        return np.zeros_like(mask)
    labels, n = ndimage.label(mask, structure=EIGHT_CONNECTED)
    small = np.bincount(labels.ravel(), minlength=n + 1) <= max_cells
    small[0] = False
    small[np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])] = False
    return small[labels]


def test_small_components_as_by_labels() -> None:
    rng = np.random.default_rng(2)
    found = 0
    for m in _masks(2, 400, (0.05, 0.9)):
        k = int(rng.integers(-1, 20))
        want = _small_by_labels(m, k)
        np.testing.assert_array_equal(small_components(m, k), want)
        found += int(want.any())
    assert found > 50


def test_frontier_clusters_as_by_labels() -> None:
    rng = np.random.default_rng(3)
    for m in _masks(3, 400, (0.05, 0.7)):
        k = int(rng.integers(0, 8))
        labels, n = ndimage.label(m, structure=EIGHT_CONNECTED)
        keep = np.bincount(labels.ravel(), minlength=n + 1) >= max(1, k)
        keep[0] = False
        remap = np.full(n + 1, -1)
        remap[keep] = np.arange(int(keep.sum()))
        of = remap[labels]
        got = cluster_frontiers(m, min_cells=k)
        np.testing.assert_array_equal(got.mask, of >= 0)
        np.testing.assert_array_equal(got.cells_rc, np.argwhere(of >= 0))
        np.testing.assert_array_equal(got.cell_cluster, of[of >= 0])
        assert len(got) == int(keep.sum())


def test_dilate_as_binary_dilation() -> None:
    four = ndimage.generate_binary_structure(2, 1)
    for m in _masks(4, 200, (0.02, 0.5)):
        np.testing.assert_array_equal(dilate(m, eight=False),
                                      ndimage.binary_dilation(m, structure=four))
        np.testing.assert_array_equal(dilate(m, eight=True),
                                      ndimage.binary_dilation(m, structure=EIGHT_CONNECTED))


def _skeleton_by_shifts(space: np.ndarray, sep: float) -> np.ndarray:
    _, near = ndimage.distance_transform_edt(space, return_indices=True)
    fr, fc = near
    ridge = np.zeros(space.shape, bool)
    h, w = space.shape
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = (slice(max(0, -dr), h - max(0, dr)), slice(max(0, -dc), w - max(0, dc)))
        b = (slice(max(0, dr), h + min(0, dr)), slice(max(0, dc), w + min(0, dc)))
        m = space[a] & space[b] & ((fr[a] - fr[b]) ** 2 + (fc[a] - fc[b]) ** 2 >= sep * sep)
        ridge[a] |= m
        ridge[b] |= m
    return np.asarray(skeletonize(ridge), bool)


def test_voronoi_skeleton_as_by_shifts() -> None:
    rng = np.random.default_rng(5)
    nonempty = 0
    for m in _masks(5, 150, (0.5, 0.95)):
        if m.all() or not m.any():
            continue
        sep = float(rng.uniform(1.0, 4.0))
        want = _skeleton_by_shifts(m, sep)
        np.testing.assert_array_equal(voronoi_skeleton(m, min_separation_cells=sep), want)
        nonempty += int(want.any())
    assert nonempty > 30


def test_thinning_is_skimages() -> None:
    """The compiled thinning visits only set cells; it gives skimage's skeleton, cell for cell,
    on blobs, noise, bands one or two cells wide and every 3 × 3 pattern."""
    rng = np.random.default_rng(11)
    masks = _masks(7, 300, (0.2, 0.95))
    masks += [ndimage.binary_opening(m) for m in masks[:150]]
    masks += [ndimage.binary_dilation(rng.random((40, 50)) < 0.02, iterations=int(k))
              for k in rng.integers(1, 4, 60)]
    masks += [np.array([(code >> k) & 1 for k in range(9)], bool).reshape(3, 3)
              for code in range(512)]
    thinned = 0
    for m in masks:
        want = np.asarray(skeletonize(m), bool)
        np.testing.assert_array_equal(thin(np.ascontiguousarray(m), REMOVAL), want)
        thinned += int(want.sum() < m.sum())
    assert thinned > 300


def test_dijkstra_trace_as_mcp_traceback() -> None:
    from skimage.graph import MCP_Geometric

    from server.planning.dijkstra import _trace

    rng = np.random.default_rng(6)
    traced = 0
    for _ in range(10):
        cost = rng.uniform(1.0, 3.0, (25, 35))
        cost[rng.random(cost.shape) < 0.25] = np.inf
        cost[4, 4] = 1.0
        mcp = MCP_Geometric(cost, fully_connected=True)
        cum, back = mcp.find_costs([(4, 4)], [(20, 30)], find_all_ends=True)
        offsets = np.asarray(mcp.offsets, dtype=np.int64)
        for r, c in np.argwhere(np.isfinite(cum)):
            want = np.asarray(mcp.traceback((r, c)), dtype=np.int64).reshape(-1, 2)
            np.testing.assert_array_equal(_trace(back, offsets, int(r), int(c)), want)
            traced += 1
    assert traced > 1000
