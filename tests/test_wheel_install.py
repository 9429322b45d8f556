"""A wheel installed far from this checkout runs the demo: its worlds ship inside the package.

The wheel is built from a copy of the sources and installed into a new environment outside the
repository, and the demo is run from an empty folder with no ``../shared`` beside it. Nothing
is fetched from the network: the new environment sees the packages this one has (the versions
``deploy/constraints.txt`` pins) through a ``.pth`` line, and the wheel alone is installed,
without its dependencies; the wheel's own ``mrslam`` is the one that runs.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import zipfile
from pathlib import Path

import pytest

from tests.conftest import ROOT

#: starts other processes (the CLI, the server, the simulator, agents, scripts): the e2e tier
pytestmark = pytest.mark.e2e

WORLD_FILES = {"sim/worlds/small_house.world", "sim/worlds/large_house.world",
               "sim/worlds/scenarios.yaml"}


def build_wheel(tmp_path: Path) -> Path:
    """The wheel of a copy of the sources (the checkout's own build folders stay untouched)."""
    src = tmp_path / "src"
    src.mkdir()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in pyproject["tool"]["setuptools"]["packages"]["find"][
        "include"]]
    for name in packages:
        shutil.copytree(ROOT / name, src / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    dist = tmp_path / "dist"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist),
                    str(src)], check=True, timeout=600)
    (wheel,) = dist.glob("mrslam-*.whl")
    return wheel


@pytest.mark.timeout(900)
def test_a_wheel_installed_elsewhere_runs_the_demo_in_its_own_worlds(tmp_path: Path) -> None:
    wheel = build_wheel(tmp_path)
    with zipfile.ZipFile(wheel) as z:
        assert set(z.namelist()) >= WORLD_FILES
        assert b"large-house-5" in z.read("sim/worlds/scenarios.yaml")

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("MRSLAM_", "PYTHON", "VIRTUAL_ENV"))}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    # the dependencies as this environment has them (a plain path: its .pth files, among them
    # this checkout's editable install, are not read)
    new_site = subprocess.run([str(venv / "bin" / "python"), "-c",
                               "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                              check=True, capture_output=True, text=True).stdout.strip()
    (Path(new_site) / "deps-of-the-tests.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n")
    pip = subprocess.run([str(venv / "bin" / "pip"), "install", "-q", "--no-compile",
                          "--no-index", "--no-deps", str(wheel)], timeout=600, env=env,
                         capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr[-3000:]

    empty = tmp_path / "elsewhere"   # nothing here, and no ../shared beside it
    empty.mkdir()
    assert not (empty.parent / "shared").exists()
    where = subprocess.run([str(venv / "bin" / "python"), "-c",
                            "import mrslam, sim.config; print(mrslam.__file__); "
                            "print(sim.config.DEFAULT_SCENARIOS)"],
                           cwd=empty, env=env, capture_output=True, text=True, check=True)
    assert all(Path(p).is_relative_to(venv) for p in where.stdout.split())

    out = tmp_path / "run"
    # a low threshold, so that 30 s of simulated time is enough to finish (exit code 0)
    res = subprocess.run([str(venv / "bin" / "mrslam"), "demo", "--max-sim-time", "30",
                          "--coverage", "0.15", "--out", str(out)],
                         cwd=empty, env=env, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["scenario"] == "small-house-3" and report["reached"]
    assert Path(report["world"]).is_relative_to(venv)          # the packaged world
    assert Path(report["world"]).name == "small_house.world"
    robots = report["robots"].values()
    assert sum(r["distance_m"] for r in robots) > 1.0 and all(r["collisions"] == 0 for r in robots)
    assert list(empty.iterdir()) == []                         # it wrote only to --out
