"""Size and time of installing mrslam into a fresh virtual environment; prints JSON.

For each set of extras (default: ``server`` and ``server,bench``) a new venv is made in a
temporary folder and ``pip install`` runs on a copy of this repository with the constraints
file CI uses (``deploy/constraints.txt``), without pip's cache. Reports the wall time, the
venv's size on disk and whether open3d (the benchmark-only dependency) came with it.

    python bench/install_size.py [--extras server server,bench] [--python python3]

Where wheels come from (PyPI, a local mirror) changes the time, not the size.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def folder_mb(path: Path) -> float:
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for f in files:
            p = Path(dirpath) / f
            if not p.is_symlink():
                total += p.stat().st_size
    return round(total / 2**20, 1)


def measure(extras: str, python: str, work: Path) -> dict[str, object]:
    venv = work / f"venv-{extras.replace(',', '-')}"
    subprocess.run([python, "-m", "venv", str(venv)], check=True)
    pip = venv / "bin" / "pip"
    t0 = time.monotonic()
    r = subprocess.run([str(pip), "install", "-q", "--no-cache-dir", "-c",
                        str(ROOT / "deploy" / "constraints.txt"), f"{work / 'src'}[{extras}]"],
                       capture_output=True, text=True)
    seconds = time.monotonic() - t0
    if r.returncode != 0:
        return {"extras": extras, "error": r.stderr.strip().splitlines()[-1:]}
    has = subprocess.run([str(venv / "bin" / "python"), "-c",
                          "import importlib.util as u; print(bool(u.find_spec('open3d')))"],
                         capture_output=True, text=True).stdout.strip() == "True"
    return {"extras": extras, "install_s": round(seconds, 1), "venv_mb": folder_mb(venv),
            "open3d": has}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extras", nargs="+", default=["server", "server,bench"])
    ap.add_argument("--python", default="python3", help="the interpreter of the new venvs")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="mrslam-install-") as tmp:
        work = Path(tmp)
        shutil.copytree(ROOT, work / "src", ignore=shutil.ignore_patterns(
            ".venv", ".git", "runs", "*.egg-info", "__pycache__", ".mypy_cache",
            ".pytest_cache", ".ruff_cache", "build"))
        rows = [measure(e, args.python, work) for e in args.extras]
    print(json.dumps({"runs": rows, "constraints": "deploy/constraints.txt"}, indent=1))


if __name__ == "__main__":
    main()
