"""Trajectories in TUM format (``timestamp x y z qx qy qz qw``, what evo reads): the server's
beside its CSVs, and the simulator's truth from the demo's report."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mrslam.report import write_truth_tum
from server.runtime.outputs import tum_lines, write_trajectory, write_tum


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps [s] and (x, y, yaw) back from a TUM file, the way evo parses it: 8 numbers a
    line, the quaternion's yaw for a rotation about z."""
    rows = np.array([[float(v) for v in line.split()] for line in path.read_text().splitlines()])
    assert rows.shape[1] == 8
    assert np.all(rows[:, 3] == 0) and np.all(rows[:, 4:6] == 0)   # planar: z, qx, qy
    assert np.allclose(np.linalg.norm(rows[:, 4:8], axis=1), 1.0, atol=1e-6)
    yaw = 2 * np.arctan2(rows[:, 6], rows[:, 7])
    return rows[:, 0], np.column_stack([rows[:, 1], rows[:, 2], np.angle(np.exp(1j * yaw))])


def test_random_trajectories_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    stamps = np.sort(rng.integers(0, 10**13, 200))
    poses = np.column_stack([rng.uniform(-50, 50, (200, 2)), rng.uniform(-math.pi, math.pi, 200)])
    write_tum(tmp_path / "r1.tum", stamps, poses)
    t, back = read_tum(tmp_path / "r1.tum")
    assert np.allclose(t, stamps * 1e-9, atol=1e-9, rtol=0)
    assert np.allclose(back[:, :2], poses[:, :2], atol=1e-5)
    assert np.allclose(np.angle(np.exp(1j * (back[:, 2] - poses[:, 2]))), 0, atol=1e-6)


def test_the_stamp_keeps_every_nanosecond() -> None:
    line = tum_lines([1_700_000_000_000_000_001], [[0.0, 0.0, 0.0]])
    assert line.split()[0] == "1700000000.000000001"


def test_the_server_writes_tum_beside_each_csv(tmp_path: Path) -> None:
    from server.runtime.outputs import Outputs

    stamps = np.arange(5, dtype=np.int64) * 10**8
    poses = np.column_stack([np.arange(5) * 0.1, np.zeros(5), np.full(5, 0.5)])
    Outputs({}, {}, {"r1_final": (stamps, poses)}, {}).write(tmp_path)
    folder = tmp_path / "trajectories"
    csv, tum = folder / "r1_final.csv", folder / "r1_final.tum"
    assert csv.exists() and tum.exists()
    t, back = read_tum(tum)
    assert np.allclose(back, poses, atol=1e-5) and np.allclose(t, stamps * 1e-9)
    write_trajectory(tmp_path / "x.csv", stamps, poses)   # the CSV is as before
    assert (tmp_path / "x.csv").read_text() == csv.read_text()


def test_the_truth_is_written_per_robot(tmp_path: Path) -> None:
    truth = {"r2": {"stamps_ns": np.array([0, 50_000_000]),
                    "poses": np.array([[1.0, 2.0, 3.0], [1.1, 2.0, -3.1]])}}
    (path,) = write_truth_tum(truth, tmp_path / "sim" / "trajectories")
    assert path.name == "r2_truth.tum"
    _, back = read_tum(path)
    assert np.allclose(back, truth["r2"]["poses"], atol=1e-5)
