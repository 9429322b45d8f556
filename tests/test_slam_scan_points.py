"""A scan's points, normals and misses from the compiled pass are those of the numpy steps
it replaced, to the bit (``tests/reference_numpy.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from server.slam.scan import ScanError, scan_to_points
from tests.reference_numpy import reference_scan_to_points


def _scans(seed: int, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        beams = int(rng.choice([0, 1, 2, 3, 40, 360, 640, 1081]))
        fov = float(rng.choice([2 * np.pi, 1.5, 4.7]))
        a = -fov / 2 + np.arange(beams) * (fov / max(beams, 1))
        room = rng.uniform(1.0, 12.0)
        r = room * (1 + 0.3 * np.sin(rng.integers(1, 6) * a)) + rng.normal(0, 0.02, beams)
        # what real sensors send: no return (inf), NaN, too near, at or past the maximum,
        # zero, depth jumps
        for bad, p in ((np.inf, 0.05), (np.nan, 0.03), (0.01, 0.03), (40.0, 0.02),
                       (55.0, 0.02), (0.0, 0.02)):
            r[rng.random(beams) < p] = bad
        jumps = rng.random(beams) < 0.05
        r[jumps] *= rng.uniform(0.3, 3.0, int(jumps.sum()))
        if beams and rng.random() < 0.1:
            a[rng.integers(0, beams)] = np.nan           # a broken angle
        if rng.random() < 0.2:
            r = r.astype(np.float32)
        out.append((r, a))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_scan_points_are_the_numpy_ones(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    kept = 0
    for r, a in _scans(seed, 250):
        args = (0.05, 40.0, int(rng.choice([2, 4])), 0.3, float(rng.choice([0.0, 0.08, 0.3])),
                float(rng.choice([0.0, 5.0])))
        got, want = scan_to_points(r, a, *args), reference_scan_to_points(r, a, *args)
        for name in ("points", "normals", "ranges_m", "hits", "misses"):
            g, w = getattr(got, name), getattr(want, name)
            assert g.shape == w.shape, name
            np.testing.assert_array_equal(g, w, err_msg=name)
        assert (got.fov_rad, got.heading_rad) == (want.fov_rad, want.heading_rad)
        kept += len(got.points)
    assert kept > 10_000


def test_ranges_and_angles_of_different_shapes_are_refused() -> None:
    with pytest.raises(ScanError, match="equal 1-D arrays"):
        scan_to_points(np.ones(10), np.zeros(9), 0.05, 40.0)


def test_read_only_inputs_use_the_kernel_compiled_at_import() -> None:
    """A wire message's ranges and a shared angle table are read-only arrays, which numba
    types apart: they must not compile another variant of the kernel on a first scan (seconds
    in a scan's time, and the compiler's memory in ``slam-log``)."""
    from server.slam.scan import _scan_kernel

    before = len(_scan_kernel.signatures)
    a = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    r = np.frombuffer((np.full(360, 2.5)).tobytes())           # read-only, as from bytes
    a_ro = a.copy()
    a_ro.setflags(write=False)
    got = scan_to_points(r, a_ro, 0.1, 10.0, min_spacing_m=0.05)
    want = scan_to_points(r.copy(), a, 0.1, 10.0, min_spacing_m=0.05)
    assert len(_scan_kernel.signatures) == before == 1
    assert np.array_equal(got.points, want.points) and len(got.points) > 100
