"""The agent's parts: what it imports, the watchdog, the detector on bad frames."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from robot_agent.aruco import TagDetector, refine_corners
from robot_agent.watchdog import Watchdog
from schemas.tags import CameraMount, TagLayout
from tests.conftest import ROOT

HEAVY = ["gtsam", "open3d", "skimage", "scipy", "server", "factors", "sim", "matplotlib"]


def test_the_agent_does_not_import_server_libraries() -> None:
    code = ("import json, sys\n"
            "import robot_agent.runtime, robot_agent.sim_backend, robot_agent.aruco\n"
            "from mrslam.cli import app\n"
            f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=60, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_watchdog_expires_once_and_server_loss_disarms() -> None:
    w = Watchdog()
    assert not w.expired(10**12)                  # no command yet: nothing to stop
    w.feed(1_000_000_000, 0.5)
    assert not w.expired(1_400_000_000)
    assert w.expired(1_600_000_000) and not w.expired(1_700_000_000)
    assert w.timeouts == 1
    w.feed(2_000_000_000, 0.5)
    w.server_lost()
    assert not w.expired(9_000_000_000) and w.server_losses == 1   # disarmed: never lapses


def test_detector_survives_blank_noise_and_odd_frames() -> None:
    det = TagDetector(TagLayout(), CameraMount())
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    rng = np.random.default_rng(0)
    for image in (np.zeros((480, 640), np.uint8),
                  rng.integers(0, 256, (480, 640), dtype=np.uint8),
                  np.full((3, 3), 255, np.uint8)):
        found = det.detect(image, K, "r1")
        assert found.sightings == []


def test_corner_refinement_keeps_corners_of_tiny_or_blank_quads() -> None:
    quad = np.array([[10.0, 10.0], [14.0, 10.0], [14.0, 14.0], [10.0, 14.0]])
    img = np.full((40, 40), 128, np.float32)
    assert np.array_equal(refine_corners(img, quad, 6), quad)        # cells below 3 px
    big = quad * 5
    assert np.array_equal(refine_corners(np.full((100, 100), 128, np.float32), big, 6), big)


def test_line_of_sight_drops_tags_behind_a_closer_return() -> None:
    import math as m

    import numpy as np

    from robot_agent.aruco import in_line_of_sight

    angles = np.linspace(-m.pi, m.pi, 400, endpoint=False)
    ranges = np.full(400, np.inf)
    # the observed robot itself (its body, 0.13 m before its centre) at 3 m, bearing 0.2 rad
    ranges[np.abs(angles - 0.2) < 0.03] = 2.87
    assert in_line_of_sight(3.0, 0.2, ranges, angles)
    # a wall at 1.5 m in that direction: seen through a gap, or not what it seems
    ranges[np.abs(angles - 0.21) < 0.01] = 1.5
    assert not in_line_of_sight(3.0, 0.2, ranges, angles)
    # the same wall well off the bearing does not matter; no-return beams never object
    assert in_line_of_sight(3.0, -1.0, ranges, angles)
    assert in_line_of_sight(3.0, 0.2, np.full(400, np.nan), angles)
