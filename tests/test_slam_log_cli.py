"""``mrslam slam-log`` and ``mrslam eval-relations`` end to end, on a slice of a real log."""

from __future__ import annotations

import bz2
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from mrslam.cli import app
from server.offline.evaluation import evaluate, match_stamps, relation_errors
from tests.conftest import DATA

CARMEN = DATA / "carmen"
N_SCANS = 300


@pytest.fixture(scope="module")
def fr079_slice(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first 300 scans of FR079 (with their ODOM lines), plus two broken lines."""
    out = tmp_path_factory.mktemp("fr079") / "fr079_head.clf"
    lines: list[str] = []
    n = 0
    with bz2.open(CARMEN / "fr079.clf.bz2", "rt") as f:
        for line in f:
            lines.append(line)
            if line.startswith("FLASER"):
                n += 1
                if n == 150:
                    lines.append("FLASER 360 1.0 2.0 truncated\n")
                    lines.append("ODOM 1 2 x 4 5 6 7 h 8\n")
                if n == N_SCANS:
                    break
    out.write_text("".join(lines))
    return out


@pytest.fixture(scope="module")
def slam_out(fr079_slice: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("out")
    res = CliRunner().invoke(app, ["slam-log", str(fr079_slice), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def test_slam_log_writes_a_pose_per_scan_maps_and_summary(slam_out: Path,
                                                           fr079_slice: Path) -> None:
    stamps_in_log = [line.split()[-3] for line in fr079_slice.read_text().splitlines()
                     if line.startswith("FLASER") and len(line.split()) > 300]
    poses = [line.split() for line in (slam_out / "poses.txt").read_text().splitlines()]
    assert [p[0] for p in poses] == stamps_in_log  # every scan, stamp exactly as written
    assert all(len(p) == 4 for p in poses)
    summary = json.loads((slam_out / "summary.json").read_text())
    assert summary["scans"] == N_SCANS
    assert summary["lines_skipped"] == 2
    assert summary["keyframes"] > 20 and summary["wall_time_s"] > 0
    meta = yaml.safe_load((slam_out / "map.yaml").read_text())
    assert (slam_out / meta["image"]).stat().st_size > 100
    assert (slam_out / "cloud.ply").read_bytes().startswith(b"ply\n")
    assert (slam_out / "config.yaml").exists()


def test_slam_log_slice_is_accurate(slam_out: Path) -> None:
    res = evaluate(slam_out / "poses.txt", CARMEN / "fr079.relations")
    assert res.matched >= 50
    assert res.unmatched == res.relations - res.matched
    assert res.trans_mean_m < 0.04
    assert res.rot_mean_deg < 0.5


def test_eval_relations_cli(slam_out: Path) -> None:
    res = CliRunner().invoke(app, ["eval-relations", str(slam_out / "poses.txt"),
                                   str(CARMEN / "fr079.relations"), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.output.strip().splitlines()[-1])
    assert data["matched"] >= 50 and data["trans_mean_m"] < 0.04
    table = CliRunner().invoke(app, ["eval-relations", str(slam_out / "poses.txt"),
                                     str(CARMEN / "fr079.relations")])
    assert table.exit_code == 0 and "translational" in table.output and "±" in table.output


def test_missing_or_unreadable_inputs_exit_2(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["slam-log", str(tmp_path / "nope.clf"), "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "no such file" in res.output and "Traceback" not in res.output
    (tmp_path / "junk.clf").write_text("not a log\n")
    res = runner.invoke(app, ["slam-log", str(tmp_path / "junk.clf"), "--out", str(tmp_path)])
    assert res.exit_code == 2 and "no laser scans" in res.output
    res = runner.invoke(app, ["eval-relations", str(tmp_path / "nope.txt"),
                              str(CARMEN / "aces.relations")])
    assert res.exit_code == 2 and "no such poses file" in res.output


def test_relation_error_known_answer(tmp_path: Path) -> None:
    # poses on a line; the reference says the second step is 0.1 m longer and turned by 2°
    (tmp_path / "poses.txt").write_text("1.000 0 0 0\n2.000 1 0 0\n3.0004 2 0 0\nbad line\n")
    (tmp_path / "rel.txt").write_text("1.0 2.0 1 0 0 0 0 0\n"
                                      "2.0 3.0 1.1 0 0 0 0 0.0349066\n"
                                      "3.0 9.0 1 0 0 0 0 0\n")
    res = evaluate(tmp_path / "poses.txt", tmp_path / "rel.txt", tolerance_s=0.001)
    assert res.matched == 2 and res.unmatched == 1 and res.skipped_lines == 1
    assert res.trans_mean_m == pytest.approx(0.05, abs=1e-6)
    assert res.rot_mean_deg == pytest.approx(1.0, abs=1e-4)


def test_relation_error_is_frame_invariant() -> None:
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    d = rng.normal(size=(20, 3)) * 0.3
    t1, r1 = relation_errors(a, b, d)
    shift = np.array([5.0, -2.0, 1.0])
    from schemas.se2 import compose

    S = np.broadcast_to(shift, a.shape)
    t2, r2 = relation_errors(compose(S, a), compose(S, b), d)
    np.testing.assert_allclose(t1, t2, atol=1e-9)
    np.testing.assert_allclose(r1, r2, atol=1e-9)


def test_match_stamps_nearest_within_tolerance() -> None:
    stamps = np.array([1.0, 2.0, 3.0])
    idx = match_stamps(stamps, np.array([0.9999, 2.0004, 2.5, 3.01, 5.0]), 0.001)
    np.testing.assert_array_equal(idx, [0, 1, -1, -1, -1])


def test_scans_released_as_they_are_fed_give_the_same_poses(fr079_slice: Path) -> None:
    """``process(release=True)`` frees each scan once fed (a long log's scans do not stay
    for the whole run) and changes nothing of the result."""
    from server.offline.slam_log import SlamLogConfig, _read, process

    cfg = SlamLogConfig()
    _, kept, _, _ = _read(fr079_slice, cfg, None, None)
    clog, freed, _, _ = _read(fr079_slice, cfg, None, None)
    clog.lasers.clear()
    kept, freed = kept[:120], freed[:120]
    a, stamps_a, _, _ = process(kept, cfg.slam)
    b, stamps_b, _, _ = process(freed, cfg.slam, release=True)
    assert stamps_a == stamps_b and len(stamps_a) == 120
    np.testing.assert_array_equal(a.scan_poses()[1], b.scan_poses()[1])
    assert all(s is None for s in freed) and all(s is not None for s in kept)


def test_packed_scans_give_back_each_scan_as_read(fr079_slice: Path) -> None:
    """A log read for ``slam-log`` keeps its scans packed (``PackedScans``): each scan comes
    back with the stamp, line, beam angles, maximum range and odometry it was read with, a
    scan without odometry as such, and in a fraction of the records' memory."""
    from server.offline.packed import PackedScans
    from server.offline.slam_log import BareScan, SlamLogConfig, read_recording

    cfg = SlamLogConfig()
    whole = read_recording(fr079_slice, cfg)
    light = read_recording(fr079_slice, cfg, stream=True)
    packed = light.scans
    assert isinstance(packed, PackedScans) and len(packed) == len(whole.scans) > 100
    assert light.clog.lasers == [] and light.clog.odometry == []
    for a, b in zip(whole.scans, packed, strict=True):
        ra, rb = a.record, b.record
        assert (rb.kind, rb.stamp_text, rb.stamp_s, rb.line_no, rb.max_range_m) == (
            ra.kind, ra.stamp_text, ra.stamp_s, ra.line_no, ra.max_range_m)
        np.testing.assert_array_equal(rb.angles_rad, ra.angles_rad)
        assert a.T_odom_laser is not None and b.T_odom_laser is not None
        np.testing.assert_array_equal(b.T_odom_laser, a.T_odom_laser)
    assert packed[-1].record.line_no == whole.scans[-1].record.line_no
    assert [s.record.line_no for s in packed[3:6]] == [
        s.record.line_no for s in whole.scans[3:6]]
    bare = PackedScans([BareScan(s.record) for s in whole.scans[:5]])
    assert all(s.T_odom_laser is None for s in bare)
    assert packed.nbytes < 100 * len(packed)


def test_scans_whose_ranges_are_read_again_give_the_same_poses(fr079_slice: Path) -> None:
    """``mrslam slam-log`` reads a CARMEN log without the scans' ranges and reads them again
    from the file as it feeds the scans (``read_recording(stream=True)``): the same poses
    as from scans read whole, the broken lines skipped alike."""
    from server.offline.slam_log import SlamLogConfig, process, read_recording

    cfg = SlamLogConfig()
    whole = read_recording(fr079_slice, cfg)
    light = read_recording(fr079_slice, cfg, stream=True)
    assert whole.lines is None and light.lines is not None
    assert light.clog.stats.skipped == whole.clog.stats.skipped
    assert all(len(s.record.ranges_m) == 0 for s in light.scans)
    a, stamps_a, _, _ = process(whole.scans[:160], cfg.slam)
    b, stamps_b, _, _ = process(light.scans[:160], cfg.slam, release=True,
                                ranges_of=light.lines.ranges)
    light.lines.close()
    assert stamps_a == stamps_b and len(stamps_a) == 160
    np.testing.assert_array_equal(a.scan_poses()[1], b.scan_poses()[1])


@pytest.mark.e2e
def test_numba_readied_without_scipys_blas_runs_the_kernels() -> None:
    """``skip_scipy_blas`` readies numba without mapping SciPy's BLAS, done by importing
    ``server.offline.slam_log`` before it loads the kernels; the compiled kernels give the
    same answers, and SciPy's BLAS still imports afterwards."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "import server.offline.slam_log\n"   # loads the kernels (server.slam) after the skip
        "assert 'numba.np.arraymath' in sys.modules\n"
        "assert 'scipy.linalg.cython_blas' not in sys.modules\n"
        "from server.jit import skip_scipy_blas\n"
        "from server.slam.icp_kernel import build_grid\n"
        "x0, y0, nx, ny, start, order = build_grid(np.array([0.0, 1.0]), np.array([0.0, 1.0]),"
        " 0.5)\n"
        "assert (nx, ny) == (5, 5) and sorted(order) == [0, 1], (nx, ny, order)\n"
        "assert 'scipy.linalg.cython_blas' not in sys.modules\n"
        "assert not skip_scipy_blas()\n"
        "import scipy.linalg.cython_blas\n"
        "print('ok')\n")
    root = Path(__file__).resolve().parent.parent
    res = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                         text=True, timeout=300, check=False)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr[-2000:]


def test_kernels_compile_without_numbas_cache_where_it_cannot_be_written(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Where numba can write its cache nowhere (a read-only install, no writable home), it
    refuses ``cache=True``; ``njit_cached`` then compiles without the cache, says so once,
    and the function gives the same answer."""
    from numba.core import caching

    from server import jit

    def add_one(x: float) -> float:
        return x + 1.0

    assert type(jit.njit_cached(add_one)._cache).__name__ == "FunctionCache"  # type: ignore[attr-defined]
    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])
    monkeypatch.setattr(jit, "_uncached", [])
    with caplog.at_level("WARNING", logger="server.jit"):
        a, b = jit.njit_cached(add_one), jit.njit_cached(add_one)
    assert type(a._cache).__name__ == "NullCache" and a(2.0) == 3.0 == b(2.0)  # type: ignore[attr-defined]
    assert len(jit._uncached) == 2 and caplog.text.count("can write its cache nowhere") == 1


def test_progress_line_only_on_a_terminal_and_cleared_when_done() -> None:
    """``slam-log``'s progress (``ScanCounter``): one line rewritten on a terminal and cleared
    at the end; nothing at all where standard error is a file or a pipe."""
    import io

    from server.offline.progress import ScanCounter

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty, pipe = Tty(), io.StringIO()
    with ScanCounter(10, tty, every_s=0.0) as bar:
        bar.update(5)
    assert "slam-log  5/10 scans  0:00" in tty.getvalue()
    assert tty.getvalue().endswith("\r") and tty.getvalue().count("\r") == 3
    with ScanCounter(10, pipe, every_s=0.0) as bar:
        bar.update(5)
    assert pipe.getvalue() == ""


def test_a_cloud_written_in_parts_is_the_cloud_written_whole(tmp_path: Path) -> None:
    """``write_ply`` of the parts a cloud is gathered in writes the same file as of the
    points joined."""
    from server.slam.export import read_ply_xy, write_ply

    rng = np.random.default_rng(0)
    parts = [rng.normal(size=(n, 2)) for n in (5, 0, 12)]
    write_ply(tmp_path / "parts.ply", parts)
    write_ply(tmp_path / "whole.ply", np.concatenate(parts))
    assert (tmp_path / "parts.ply").read_bytes() == (tmp_path / "whole.ply").read_bytes()
    assert len(read_ply_xy(tmp_path / "parts.ply")) == 17
