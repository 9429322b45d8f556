"""Benchmark: our point-to-line matcher against Open3D's point-to-plane ICP (with 2D normals),
each as the scan matcher of the same SLAM pipeline on the real CARMEN logs.

Prints one JSON line per (log, matcher): relation errors, SLAM time in this process (reading
the log excluded), the time spent inside the matcher, and Open3D's import time. Open3D gets the
same scan points, map points and normals, the same initial guess and a 0.3 m correspondence
radius; it has no odometry prior, so along featureless corridors it slides where ours keeps
the odometry.

    .venv/bin/python bench/icp_compare.py [--logs aces fr079 mit-csail] [--scans N]

Needs the ``bench`` extra (open3d): ``deploy/bootstrap.sh all,dev,bench``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "carmen"

from server.offline.evaluation import evaluate  # noqa: E402
from server.offline.logs import attach_odometry, read_log, select_stream  # noqa: E402
from server.offline.slam_log import process  # noqa: E402
from server.slam import frontend  # noqa: E402
from server.slam.config import SlamConfig  # noqa: E402
from server.slam.icp import IcpParams, MatchResult, PointMap, translation_degeneracy  # noqa: E402

O3D_RADIUS_M = 0.3


def make_open3d_icp() -> tuple[Any, float]:
    t0 = time.perf_counter()
    try:
        import open3d as o3d
    except ImportError:
        sys.exit("icp_compare: open3d is not installed; it is the bench extra: "
                 "pip install -e '.[bench]' (or deploy/bootstrap.sh all,dev,bench)")

    import_s = time.perf_counter() - t0
    reg = o3d.pipelines.registration
    cache: dict[int, Any] = {}

    def cloud(points: np.ndarray, normals: np.ndarray | None = None) -> Any:
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(np.c_[points, np.zeros(len(points))])
        if normals is not None:  # 2D normals: Open3D's own estimate would point along z
            pc.normals = o3d.utility.Vector3dVector(np.c_[normals, np.zeros(len(normals))])
        return pc

    def icp(pts: np.ndarray, nrm: np.ndarray | None, target: PointMap, T_init: np.ndarray,
            p: IcpParams, prior_info: np.ndarray | None = None) -> MatchResult:
        dst = cache.get(id(target))
        if dst is None:
            cache.clear()
            dst = cache[id(target)] = cloud(target.points, target.normals)
        c, s = math.cos(T_init[2]), math.sin(T_init[2])
        M0 = np.eye(4)
        M0[:2, :2] = [[c, -s], [s, c]]
        M0[:2, 3] = T_init[:2]
        r = reg.registration_icp(cloud(pts), dst, O3D_RADIUS_M, M0,
                                 reg.TransformationEstimationPointToPlane(),
                                 reg.ICPConvergenceCriteria(1e-6, 1e-6, p.max_iterations))
        M = np.asarray(r.transformation)
        T = np.array([M[0, 3], M[1, 3], math.atan2(M[1, 0], M[0, 0])])
        corr = np.asarray(r.correspondence_set)
        if len(corr) < 6:
            return MatchResult(T, np.zeros((3, 3)), float("inf"), 0.0, 0, False, None)
        q = pts[corr[:, 0]] @ M[:2, :2].T + M[:2, 3]
        n = target.normals[corr[:, 1]]
        res = np.sum(n * (q - target.points[corr[:, 1]]), axis=1)
        rq = q - M[:2, 3]
        J = np.stack([n[:, 0], n[:, 1], n[:, 1] * rq[:, 0] - n[:, 0] * rq[:, 1]])
        H = J @ J.T
        sigma2 = max(float(res @ res) / max(len(res) - 3, 1), 1e-6)
        inl = float(np.count_nonzero(np.abs(res) < p.inlier_m)) / max(len(pts), 1)
        return MatchResult(T, H / sigma2, math.sqrt(float(res @ res) / len(res)), inl, 0, True,
                           translation_degeneracy(H, p.degenerate_eigen_ratio))

    return icp, import_s


def run(name: str, matcher: str, n_scans: int) -> dict[str, Any]:
    clog = read_log(DATA / f"{name}.clf.bz2")
    scans = attach_odometry(select_stream(clog), clog.odometry)
    if n_scans:
        scans = scans[:n_scans]
    original = frontend.icp
    import_s = 0.0
    if matcher == "open3d":
        fn, import_s = make_open3d_icp()
    else:
        fn = original
    spent = [0.0]

    def timed(*args: Any) -> MatchResult:
        t = time.perf_counter()
        out = fn(*args)
        spent[0] += time.perf_counter() - t
        return out

    frontend.icp = timed  # type: ignore[assignment]
    try:
        t0 = time.perf_counter()
        slam, stamps, _, _ = process(scans, SlamConfig())
        slam_s = time.perf_counter() - t0
    finally:
        frontend.icp = original
    _, poses = slam.scan_poses()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "poses.txt"
        path.write_text("".join(f"{t} {x} {y} {th}\n" for t, (x, y, th)
                                in zip(stamps, poses, strict=True)))
        res = evaluate(path, DATA / f"{name}.relations")
    return {"log": name, "matcher": matcher, "scans": len(scans),
            "trans_error_m": round(res.trans_mean_m, 4),
            "rot_error_deg": round(res.rot_mean_deg, 3),
            "relations_matched": res.matched, "slam_time_s": round(slam_s, 2),
            "front_end_match_time_s": round(spent[0], 2), "import_time_s": round(import_s, 2),
            "match_kinds": slam.stats.matches}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--logs", nargs="+", default=["aces", "fr079", "mit-csail"])
    ap.add_argument("--scans", type=int, default=0, help="only the first N scans (0: all)")
    args = ap.parse_args()
    for name in args.logs:
        for matcher in ("ours", "open3d"):
            print(json.dumps(run(name, matcher, args.scans)), flush=True)


if __name__ == "__main__":
    main()
