"""The install's shape: open3d only in the bench extra, compatible-release bounds on the core
libraries, and a constraints file (what CI installs) that pins every requirement to a version
the ranges of pyproject.toml allow."""

from __future__ import annotations

import re
import tomllib

from packaging.requirements import Requirement
from packaging.version import Version

from tests.conftest import ROOT

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
EXTRAS: dict[str, list[str]] = PYPROJECT["project"]["optional-dependencies"]


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins() -> dict[str, Version]:
    out = {}
    for line in (ROOT / "deploy" / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, version = line.partition("==")
            out[norm(name)] = Version(version)
    return out


def requirements() -> list[Requirement]:
    return [Requirement(r) for r in [*PYPROJECT["project"]["dependencies"],
                                     *(r for rs in EXTRAS.values() for r in rs)]
            if not r.startswith("mrslam")]


def test_open3d_is_only_in_the_bench_extra() -> None:
    for extra, reqs in EXTRAS.items():
        names = {norm(Requirement(r).name) for r in reqs}
        assert ("open3d" in names) == (extra == "bench"), extra
    assert "bench" not in EXTRAS["all"][0]


def test_the_core_libraries_have_compatible_release_bounds() -> None:
    for req in requirements():
        if norm(req.name) in ("gtsam", "eclipse-zenoh", "opencv-contrib-python-headless"):
            assert [s.operator for s in req.specifier] == ["~="], req


def test_the_constraints_pin_every_requirement_within_its_range() -> None:
    pinned = pins()
    for req in requirements():
        version = pinned.get(norm(req.name))
        assert version is not None, f"{req.name} is not in deploy/constraints.txt"
        assert req.specifier.contains(version, prereleases=True), (req, version)


def test_bootstrap_installs_with_the_constraints_and_libusb_only_for_bench() -> None:
    text = (ROOT / "deploy" / "bootstrap.sh").read_text()
    assert "-c deploy/constraints.txt" in text
    (libusb_guard,) = [line for line in text.splitlines() if "extras" in line and "if [[" in line
                       and "bench" in line]
    assert "server" not in libusb_guard and "all" not in libusb_guard
