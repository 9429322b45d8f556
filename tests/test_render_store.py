"""What a keyframe keeps only to draw the map: on disk, carried whole when pickled, and in
memory where no file can be made."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from server.slam import render_store
from server.slam.keyframes import Keyframe
from server.slam.render_store import RenderScan
from server.slam.scan import ScanPoints


def scan_points(reach_m: float = 10.0, n: int = 360, seed: int = 0) -> ScanPoints:
    rng = np.random.default_rng(seed)
    a = np.linspace(-np.pi, np.pi, n, endpoint=False)
    r = rng.uniform(0.2, reach_m, n)
    pts = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    normals = -pts / r[:, None]
    normals[::7] = np.nan                                  # some points without a normal
    misses = pts[:20] * 1.5
    return ScanPoints(pts, normals, r, pts, misses)


def test_the_map_points_are_kept_in_single_precision_as_before() -> None:
    sc = scan_points(80.0)                                  # an 80 m laser
    kf = Keyframe.create(0, 0, sc, np.zeros(3))
    assert kf.hits.dtype == np.float32 and kf.misses.dtype == np.float32
    assert np.array_equal(kf.hits, sc.hits.astype(np.float32))
    assert np.array_equal(kf.misses, sc.misses.astype(np.float32))
    assert not kf.hits.flags.writeable


def test_a_keyframe_keeps_its_map_points_on_disk_not_in_memory(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("MRSLAM_RENDER_DIR", str(tmp_path))
    monkeypatch.setattr(render_store, "_store", None)
    sc = scan_points()
    kf = Keyframe.create(3, 7, sc, np.zeros(3))
    assert kf.render.on_disk and kf.render.nbytes == 0
    assert list(tmp_path.iterdir()) == []                  # unlinked: never left behind
    assert np.array_equal(kf.hits, sc.hits.astype(np.float32))
    assert np.array_equal(kf.misses, sc.misses.astype(np.float32))
    # matching keeps only the points with a normal, in double precision, read-only
    ok = np.isfinite(sc.normals[:, 0])
    assert np.array_equal(kf.matchable.points, sc.points[ok])
    assert not kf.matchable.points.flags.writeable
    off = Keyframe.create(4, 8, sc, np.zeros(3), spill=False)
    assert not off.render.on_disk and off.render.nbytes == (len(sc.hits) + 20) * 8
    assert np.array_equal(off.hits, kf.hits)


def test_a_pickled_keyframe_carries_its_points_not_a_place_in_a_file() -> None:
    kf = Keyframe.create(1, 2, scan_points(), np.array([1.0, 2.0, 0.3]))
    blob = pickle.dumps(kf)
    # another process has no such file: it must read the points from the pickle alone
    code = ("import pickle, sys, numpy as np; kf = pickle.load(sys.stdin.buffer); "
            "print(len(kf.hits), float(np.abs(kf.hits).sum()), kf.render.on_disk)")
    out = subprocess.run([sys.executable, "-c", code], input=blob, capture_output=True,
                         check=True, cwd=Path(__file__).resolve().parents[1]).stdout.split()
    assert int(out[0]) == len(kf.hits)
    assert float(out[1]) == pytest.approx(float(np.abs(kf.hits).sum()))
    assert out[2] == b"True"
    back = pickle.loads(blob)
    assert np.array_equal(back.hits, kf.hits) and np.array_equal(back.misses, kf.misses)
    assert back.render.stored().flags.writeable is False     # a snapshot stores it once


def test_a_forked_child_reads_its_parents_keyframes_and_writes_its_own() -> None:
    parent = Keyframe.create(1, 2, scan_points(seed=1), np.zeros(3))
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:                                           # the child
        ok = np.array_equal(parent.hits, parent.hits)
        mine = Keyframe.create(2, 3, scan_points(seed=2), np.zeros(3))
        ok = ok and mine.render._store is not parent.render._store
        ok = ok and np.allclose(mine.hits, scan_points(seed=2).hits, atol=1e-3)
        os.write(w, b"1" if ok else b"0")
        os._exit(0)
    os.close(w)
    assert os.read(r, 1) == b"1"
    os.waitpid(pid, 0)
    # the parent's file was not written over by the child
    assert np.allclose(parent.hits, scan_points(seed=1).hits, atol=1e-3)


def test_a_folder_that_cannot_hold_the_file_falls_back_to_temp_then_to_memory(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, caplog: pytest.LogCaptureFixture
        ) -> None:
    import tempfile

    monkeypatch.setenv("MRSLAM_RENDER_DIR", str(tmp_path / "missing"))
    monkeypatch.setattr(render_store, "_store", None)
    monkeypatch.setattr(render_store, "_store_failed", False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    sc = scan_points()
    kf = Keyframe.create(0, 0, sc, np.zeros(3))
    assert kf.render.on_disk and "go to" in caplog.text and "missing" in caplog.text
    # nowhere to write at all: in memory, said once
    monkeypatch.setattr(render_store, "_store", None)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "also-missing"))
    kf = Keyframe.create(1, 0, sc, np.zeros(3))
    assert not kf.render.on_disk and kf.render.nbytes > 0
    assert np.array_equal(kf.hits, sc.hits.astype(np.float32))
    assert "stay in memory" in caplog.text
    assert not Keyframe.create(2, 0, sc, np.zeros(3)).render.on_disk
    assert caplog.text.count("stay in memory") == 1


def test_the_server_puts_the_file_in_its_state_folder(monkeypatch: pytest.MonkeyPatch,
                                                     tmp_path: Path) -> None:
    from server.config import ServerConfig
    from server.runtime.daemon import _resume

    monkeypatch.delenv("MRSLAM_RENDER_DIR", raising=False)
    monkeypatch.setattr(render_store, "_store", None)
    monkeypatch.setattr(render_store, "_folder", None)
    state = tmp_path / "state"
    state.mkdir()
    cfg = ServerConfig.model_validate({"state_dir": str(state)})
    _resume(cfg)
    assert render_store._folder == str(state)
    store = render_store.store()
    assert store is not None
    assert os.readlink(f"/proc/self/fd/{store._fd}").startswith(str(state))


def test_non_finite_points_are_not_drawn() -> None:
    hits = np.array([[1.0, 2.0], [np.nan, 1.0], [3.0, -4.0]])
    rs = RenderScan.of(hits, np.zeros((0, 2)))
    assert rs.n_hits == 2 and np.allclose(rs.hits, [[1.0, 2.0], [3.0, -4.0]])
