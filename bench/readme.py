"""The README's demo run: ``make demo`` (the default demo: lockstep, seed 0) as the README
quotes it; prints JSON.

Runs ``mrslam demo`` with its defaults in a scratch folder, and prints what the README says of
it (``bench/support/readme_run.py``): who joined whom and when, the time to the threshold, the
console's output. ``--write`` makes the README show this run: ``docs/img/demo-run.json``,
``docs/img/merged-map.png`` (the final team's map) and the README's caption and sample output.
A lockstep run gives the same figures every time, so a change in them is a change in what the
robots did.

    python bench/readme.py [--write] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

_HERE = Path(__file__).resolve().parent
# run as a script, this folder comes first on sys.path and bench/sim.py would hide the
# simulator package: look in the repository instead
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

from bench.support import readme_run  # noqa: E402

#: the README's sample output is as wide as its text
COLUMNS = 80


def demo(scratch: Path) -> tuple[Path, str]:
    """``mrslam demo`` with its defaults, run from ``scratch`` (so its run folder is
    ``runs/<scenario>-<date>-<time>`` there, as on a fresh clone); the run folder and what the
    demo printed."""
    env = dict(os.environ, COLUMNS=str(COLUMNS), PYTHONPATH=str(_HERE.parent))
    res = subprocess.run([sys.executable, "-m", "mrslam", "demo"], cwd=scratch, env=env,
                         capture_output=True, text=True, timeout=1800)
    if res.returncode != 0:
        raise SystemExit(f"the demo failed (exit {res.returncode}):\n{res.stderr[-3000:]}")
    folder = max((scratch / "runs").iterdir(), key=lambda p: p.stat().st_mtime)
    return folder, res.stderr


def reference(folder: Path, console: str) -> dict[str, Any]:
    report = json.loads((folder / "report.json").read_text())
    final = [tid for tid, t in report["teams"].items() if not t.get("merged_into")]
    team = max(final, key=lambda tid: len(report["teams"][tid]["robot_ids"]))
    return {"figures": readme_run.figures(report),
            "output": readme_run.sample_output(console, f"runs/{folder.name}"),
            "map": f"map_{team}.png",
            "map_sha256": readme_run.sha256(folder / f"map_{team}.png")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true",
                    help="make docs/img/demo-run.json, docs/img/merged-map.png and the README "
                    "from this run")
    ap.add_argument("--out", type=Path, help="keep the run here (default: a scratch folder)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="mrslam-readme-") as tmp:
        scratch = args.out or Path(tmp)
        scratch.mkdir(parents=True, exist_ok=True)
        folder, console = demo(scratch)
        ref = reference(folder, console)
        if args.write:
            shutil.copyfile(folder / ref["map"], readme_run.MAP_PNG)
            readme_run.REFERENCE.write_text(json.dumps(ref, indent=1, ensure_ascii=False)
                                            + "\n")
            readme_run.README.write_text(readme_run.splice(readme_run.README.read_text(), ref))
    print(json.dumps(ref, indent=1, ensure_ascii=False))


if __name__ == "__main__":
    main()
