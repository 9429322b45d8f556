"""Benchmark: ``mrslam slam-log`` on real recordings — every CARMEN log in
``../shared/data/carmen``, every bag in ``../shared/data/bags``, and any path given.

Prints one JSON line per recording: scans in the file (counted by this checkout's reader),
scans posed (lines of ``poses.txt``), the share posed, relations scored and unscored and the
relation errors (mean ± std, translational [m] and rotational [deg]) where a ``.relations``
file lies beside the recording, odometry samples skipped as corrupt, and seconds (wall, one
fresh process pinned to one core: ``bench/slam_logs.run_child``). With ``--base DIR`` the same
figures from the checkout at DIR (another commit's, e.g. ``git worktree add /tmp/base main``)
under ``base``, and both runs' errors on the relations both scored (``common_relations``: a
run that drops scans scores fewer relations, so its mean is over others), which says whether
the accuracy is no worse. A last line sums up the goals: at least
99.5 % of scans posed on every recording, no relation without a pose, accuracy no worse.

    .venv/bin/python bench/realdata.py [PATH ...] [--jitter LOG ...] [--base DIR] [--maps DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]
sys.path.insert(0, str(ROOT))

from bench.slam_logs import run_child  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
GOAL_POSED_PERCENT = 99.5
SUFFIXES = (".bz2", ".gz", ".clf", ".log", ".bag")


def recordings(extra: list[Path]) -> list[Path]:
    found = sorted((SHARED / "carmen").glob("*.clf*")) + sorted((SHARED / "bags").glob("*.bag"))
    return found + extra


def stem(path: Path) -> str:
    name = path.name
    while Path(name).suffix in SUFFIXES:
        name = Path(name).stem
    return name


def jittered(name: str, out_dir: Path, every: int = 15, behind_s: float = 0.006) -> Path:
    """A copy of the shared CARMEN log ``name`` in which every ``every``-th FLASER line is
    stamped ``behind_s`` before the FLASER line above it — the Intel Research Lab log's pattern
    (6.4 % of its scans, e.g. 976052862.222 after 976052862.228) — with its relations moved to
    the same stamps."""
    import bz2

    import numpy as np

    with bz2.open(SHARED / "carmen" / f"{name}.clf.bz2", "rt") as f:
        lines = f.readlines()
    flaser = [i for i, line in enumerate(lines) if line.startswith("FLASER")]
    moved: dict[float, str] = {}
    for k in range(every, len(flaser), every):
        words = lines[flaser[k]].split()
        before = lines[flaser[k - 1]].split()[-3]
        decimals = len(words[-3].partition(".")[2])
        new = f"{float(before) - behind_s:.{decimals}f}"
        moved[float(words[-3])] = new
        words[-3] = new
        lines[flaser[k]] = " ".join(words) + "\n"
    out = out_dir / f"{name}-jitter.clf"
    out.write_text("".join(lines))
    old = np.array(sorted(moved))
    rel = []
    for row in (SHARED / "carmen" / f"{name}.relations").read_text().splitlines():
        words = row.split()
        for j in (0, 1):
            t = float(words[j])
            i = int(np.clip(np.searchsorted(old, t), 1, len(old) - 1))
            near = min((i - 1, i), key=lambda m: abs(old[m] - t))
            if abs(old[near] - t) < 1e-4:
                words[j] = moved[float(old[near])]
        rel.append(" ".join(words) + "\n")
    (out_dir / f"{name}-jitter.relations").write_text("".join(rel))
    return out


def scans_in_file(path: Path) -> int:
    """Scans of the stream ``slam-log`` maps, as this checkout's reader finds them."""
    from server.offline.slam_log import SlamLogConfig, read_recording

    return len(read_recording(path, SlamLogConfig()).scans)


def run(path: Path, out: Path, core: int, root: Path, n_file: int,
        relations: Path | None) -> dict[str, Any]:
    """One ``slam-log`` run of the checkout at ``root``, with its figures."""
    from server.offline.evaluation import evaluate

    child = run_child(path, out, core, root=root)
    got: dict[str, Any] = {"seconds": round(child.wall_s, 2), "cpu_seconds": round(child.cpu_s, 2)}
    if child.returncode != 0:
        lines = child.stderr.strip().splitlines() or ["?"]
        return {**got, "error": f"exit {child.returncode}: {lines[-1][:300]}", "scans_posed": 0,
                "posed_percent": 0.0}
    posed = len((out / "poses.txt").read_text().splitlines())
    summary = json.loads((out / "summary.json").read_text())
    bag = summary.get("bag") or {}
    got.update(scans_posed=posed, posed_percent=round(100.0 * posed / max(n_file, 1), 3),
               odometry_samples=bag.get("odometry_samples"),
               odometry_skipped=bag.get("odometry_skipped"),
               odometry_source=summary.get("odometry_source"),
               stamps_early_kept=summary.get("stamps_early_kept"),
               stamps_dropped=summary["stamps_dropped_ahead"] + summary["stamps_dropped_behind"])
    if relations is not None:
        res = evaluate(out / "poses.txt", relations)
        got.update(relations_scored=res.matched, relations_unscored=res.unmatched,
                   trans_error_m=round(res.trans_mean_m, 4),
                   trans_error_std_m=round(res.trans_std_m, 4),
                   rot_error_deg=round(res.rot_mean_deg, 3),
                   rot_error_std_deg=round(res.rot_std_deg, 3))
    return got


def save_map(out: Path, dest: Path, scale: int = 4, margin: int = 6) -> None:
    """The map image cut to what was seen (and ``margin`` cells round it), enlarged ``scale``
    times cell for cell (for the docs)."""
    import cv2
    import numpy as np

    img = cv2.imread(str(out / "map.png"), cv2.IMREAD_GRAYSCALE)
    if img is None:
        return
    rows, cols = np.nonzero(img != 205)          # 205: unknown in a nav2 trinary map
    if len(rows):
        r0, c0 = max(rows.min() - margin, 0), max(cols.min() - margin, 0)
        img = img[r0:rows.max() + margin + 1, c0:cols.max() + margin + 1]
    big = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(dest), big, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def on_common_relations(relations: Path, now: Path, base: Path, tmp: Path
                        ) -> dict[str, Any] | None:
    """Both runs' errors on the relations both scored (a run that dropped scans scores fewer
    relations, and its mean is then over other ones): the like-for-like comparison."""
    from server.offline.evaluation import (
        DEFAULT_TOLERANCE_S,
        EvaluationError,
        evaluate,
        match_stamps,
        read_poses,
    )

    if not (now / "poses.txt").is_file() or not (base / "poses.txt").is_file():
        return None
    rows = [r for r in relations.read_text().splitlines() if r.split()]
    keep = None
    for run_dir in (now, base):
        stamps = read_poses(run_dir / "poses.txt")[0]
        t = [[float(w) for w in r.split()[:2]] for r in rows]
        hit = (match_stamps(stamps, [a for a, _ in t], DEFAULT_TOLERANCE_S) >= 0) & \
            (match_stamps(stamps, [b for _, b in t], DEFAULT_TOLERANCE_S) >= 0)
        keep = hit if keep is None else keep & hit
    assert keep is not None
    common = tmp / f"{relations.stem}-common.relations"
    common.write_text("".join(r + "\n" for r, k in zip(rows, keep, strict=True) if k))
    try:
        a, b = evaluate(now / "poses.txt", common), evaluate(base / "poses.txt", common)
    except EvaluationError:
        return None
    return {"relations": a.matched,
            "now_m_deg": [round(a.trans_mean_m, 4), round(a.rot_mean_deg, 3)],
            "base_m_deg": [round(b.trans_mean_m, 4), round(b.rot_mean_deg, 3)],
            "not_worse": a.trans_mean_m <= b.trans_mean_m + 5e-5
            and a.rot_mean_deg <= b.rot_mean_deg + 5e-4}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("paths", nargs="*", type=Path, help="more logs or bags")
    ap.add_argument("--base", type=Path, help="a checkout of the commit to compare with")
    ap.add_argument("--maps", type=Path, help="save each map (enlarged) here as NAME.png")
    ap.add_argument("--keep", type=Path, help="keep the outputs in this folder")
    ap.add_argument("--core", type=int, default=0, help="CPU core to pin the child to")
    ap.add_argument("--jitter", nargs="*", default=[], metavar="LOG",
                    help="also a copy of these shared CARMEN logs (aces, fr079, mit-csail) with "
                    "the Intel log's stamp jitter")
    args = ap.parse_args()
    goals = {"posed": True, "relations": True, "accuracy": True}
    with tempfile.TemporaryDirectory() as tmp:
        base_dir = args.keep or Path(tmp)
        base_dir.mkdir(parents=True, exist_ok=True)
        extra = [jittered(name, base_dir) for name in args.jitter]
        for path in recordings(args.paths + extra):
            name = stem(path)
            rel = path.parent / f"{name}.relations"
            relations = rel if rel.is_file() else None
            try:
                n_file = scans_in_file(path)
            except Exception as e:   # a recording this checkout cannot read at all
                n_file = 0
                print(f"{name}: unreadable: {e}", file=sys.stderr)
            row: dict[str, Any] = {"file": path.name, "scans_in_file": n_file}
            row.update(run(path, base_dir / name, args.core, ROOT, n_file, relations))
            if args.maps and "error" not in row:
                args.maps.mkdir(parents=True, exist_ok=True)
                save_map(base_dir / name, args.maps / f"{name}.png")
            if args.base:
                row["base"] = run(path, base_dir / f"{name}-base", args.core, args.base,
                                  n_file, relations)
                if relations is not None:
                    common = on_common_relations(relations, base_dir / name,
                                                 base_dir / f"{name}-base", base_dir)
                    row["common_relations"] = common
                    row["accuracy_not_worse"] = None if common is None else common["not_worse"]
                    goals["accuracy"] &= row["accuracy_not_worse"] is not False
            goals["posed"] &= row["posed_percent"] >= GOAL_POSED_PERCENT
            goals["relations"] &= not row.get("relations_unscored", 0)
            print(json.dumps(row), flush=True)
    print(json.dumps({"goal_posed_percent": GOAL_POSED_PERCENT,
                      "every_recording_posed": goals["posed"],
                      "no_relation_unscored": goals["relations"],
                      "accuracy_not_worse": goals["accuracy"] if args.base else None}))


if __name__ == "__main__":
    main()
