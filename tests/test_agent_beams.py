"""Sweeps of (angle, range) samples onto fixed beams without losing samples (issue 20, item 7)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_agent.drivers import rplidar_protocol as proto
from robot_agent.drivers.beams import to_beams
from robot_agent.lidar_dump import format_sweep


def positions(angles_rad: np.ndarray, beams: int) -> np.ndarray:
    """Where each sample sits, in beams from beam 0."""
    return np.remainder((angles_rad + math.pi) * beams / (2 * math.pi), beams)


@st.composite
def even_sweeps(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, int]:
    """As many samples as beams, evenly spaced from any phase, each off by up to 0.2 beam."""
    beams = draw(st.integers(8, 720))
    phase = draw(st.floats(0.0, 1.0, exclude_max=True))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    jitter = draw(st.sampled_from([0.0, 0.05, 0.2])) * rng.uniform(-1, 1, beams)
    angles = (np.arange(beams) + phase + jitter) * 2 * math.pi / beams - math.pi
    ranges = rng.permutation(np.arange(1, beams + 1)).astype(float)   # all different
    return angles, ranges, beams


@given(even_sweeps())
@settings(max_examples=100, deadline=None)
def test_as_many_beams_as_samples_keeps_every_sample(sweep: tuple[np.ndarray, np.ndarray,
                                                                 int]) -> None:
    angles, ranges, beams = sweep
    out = to_beams(angles, ranges, beams)
    assert np.isfinite(out).all()
    assert sorted(out.tolist()) == sorted(ranges.tolist())   # each sample in a beam of its own
    # and none moved more than a beam: ranges are 1..n, so a return names its sample
    sample = np.argsort(ranges)[np.rint(out).astype(int) - 1]
    d = np.abs(positions(angles, beams)[sample] - np.arange(beams)) % beams
    assert np.all(np.minimum(d, beams - d) <= 1.0 + 1e-9)


@st.composite
def any_sweeps(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, int]:
    """Any number of samples at any angles, some without a return."""
    beams = draw(st.integers(8, 400))
    n = draw(st.integers(0, 3 * beams))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    angles = rng.uniform(-4.0, 4.0, n)
    ranges = rng.uniform(0.1, 10.0, n)
    ranges[rng.random(n) < 0.1] = np.inf
    return angles, ranges, beams


@given(any_sweeps())
@settings(max_examples=100, deadline=None)
def test_no_range_is_made_up_and_no_obstacle_is_lost(sweep: tuple[np.ndarray, np.ndarray,
                                                                  int]) -> None:
    angles, ranges, beams = sweep
    out = to_beams(angles, ranges, beams)
    pos = positions(angles, beams)
    d = np.abs(pos[:, None] - np.arange(beams)[None, :]) % beams
    near = np.minimum(d, beams - d) <= 1.0 + 1e-9          # (sample, beam) within a beam
    # a beam's return is a sample's, taken at most a beam away
    for b in np.flatnonzero(np.isfinite(out)):
        assert np.any(near[:, b] & (ranges == out[b]))
    # every return is kept, or a nearer one stands within a beam
    nearest_around = np.where(near, out[None, :], np.inf).min(axis=1)
    assert np.all(nearest_around[np.isfinite(ranges)] <= ranges[np.isfinite(ranges)])


def test_a_real_gap_stays_empty() -> None:
    beams = 360
    deg = np.arange(360) + 0.5
    keep = (deg < 100) | (deg > 104)          # no samples between 100° and 104°
    angles = np.radians(deg[keep]) - math.pi
    ranges = 1.0 + 0.01 * np.arange(keep.sum())
    out = to_beams(angles, ranges, beams)
    beam_deg = np.arange(beams) * 360.0 / beams
    inside = (beam_deg > 101.5) & (beam_deg < 103.5)   # more than a beam from any sample
    assert inside.sum() == 2 and np.isinf(out[inside]).all()
    # and around it every sample still has a beam of its own
    assert sorted(out[np.isfinite(out)].tolist()) == sorted(ranges.tolist())


def revolution(angle_deg: np.ndarray, distance_mm: np.ndarray) -> proto.Revolution:
    return proto.Revolution(stamp_ns=1, angle_deg=angle_deg, distance_mm=distance_mm,
                            quality=np.full(len(angle_deg), 40))


def test_half_degree_samples_fill_every_beam() -> None:
    # the case: one sample per degree at 0.5°, 1.5°, ..., one beam per degree
    angle_deg = np.arange(360) + 0.5
    distance_mm = 1000.0 + 2.0 * np.arange(360)
    sweep = proto.to_sweep(revolution(angle_deg, distance_mm), 360, 150, 12000)
    r = np.frombuffer(sweep.ranges_mm, "<u2")
    assert np.count_nonzero(r) == 360
    assert sorted(r.tolist()) == sorted(np.rint(distance_mm).astype(int).tolist())
    # what lidar-dump prints: 360 pairs, none of them a no-return
    fields = format_sweep(sweep).split()
    assert int(fields[1]) == 360 and "inf" not in fields[2:]
    # nearest-beam rounding, as before, left beams empty
    theta = proto.robot_angles_rad(angle_deg)
    rounded = np.rint((theta + math.pi) / (2 * math.pi / 360)).astype(int) % 360
    assert len(set(rounded.tolist())) < 300


def test_samples_without_a_return_or_out_of_range_are_no_returns() -> None:
    angle_deg = np.arange(360) + 0.5
    distance_mm = np.full(360, 1000.0)
    distance_mm[10] = 0.0        # no return
    distance_mm[20] = 20000.0    # beyond range_max
    sweep = proto.to_sweep(revolution(angle_deg, distance_mm), 360, 150, 12000)
    r = np.frombuffer(sweep.ranges_mm, "<u2")
    assert np.count_nonzero(r) == 358 and set(r[r > 0].tolist()) == {1000}
