"""A recorded demo run replayed into a fresh server gives the same poses and map.

The live run is the real demo (server, simulator, agent and recorder as processes on loopback).
Its robot messages are then replayed, as fast as the link takes them, into a new server node
with the live run's configuration; the server handles one robot's scans in stamp order and its
algorithms depend only on the scans, so the outputs must match exactly.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import yaml

from mrslam.demo import run as demo
from recording.reader import read_recording
from recording.replay import run as replay
from schemas.bus import Bus, free_local_endpoint
from schemas.config import BusConfig
from schemas.config_loading import load_config
from server.config import ServerConfig
from server.runtime.node import ServerNode
from server.runtime.outputs import write_outputs
from tests.test_demo_e2e import three_rooms

#: starts other processes (the CLI, the server, the simulator, agents, scripts): the e2e tier
pytestmark = pytest.mark.e2e


def test_replayed_session_gives_the_live_runs_poses_and_map(tmp_path: Path) -> None:
    world = three_rooms(tmp_path)
    live = tmp_path / "live"
    demo({"scenario": None, "world": str(world), "robots": {"r1": (1.5, 5.5, -0.5)},
          "cells_per_m": 15, "max_sim_time_s": 40, "wall_timeout_s": 240, "out": str(live)},
         progress=False)
    rec = read_recording(live / "run.mcap")
    assert rec.report.intact
    topics = {m.topic for m in rec.messages}
    assert {"mrslam/robot/r1/scan", "mrslam/robot/r1/cmd_vel", "mrslam/server/map",
            "mrslam/sim/clock"} <= topics
    live_summary = json.loads((live / "server" / "summary.json").read_text())
    assert not live_summary["dropped_scans"]
    online = (live / "server" / "trajectories" / "r1_online.csv").read_text().splitlines()
    n_live = live_summary["robots"]["r1"]["scans"]
    assert n_live == len(online) - 1 > 100
    last_stamp_ns = int(online[-1].split(",")[0])

    endpoint = free_local_endpoint()
    cfg = load_config(ServerConfig, live / "server.yaml", {
        "bus": {"listen": [endpoint]}, "queue_per_robot": 100_000, "exit_when_done": False,
        # the recording's own stamps are the only clock a replay at full speed has
        "clock": {"source": "stamps"}})
    with Bus.open("router", listen=[endpoint]) as bus:
        node = ServerNode(bus, cfg)
        node.start()
        sent = replay(live / "run.mcap", BusConfig(connect=[endpoint]), speed=0,
                      only=["mrslam/robot/*/scan", "mrslam/robot/*/tags"],
                      until_ns=last_stamp_ns)
        assert sent["by_type"]["Scan"] == n_live
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and \
                ("r1" not in node.core.robots or node.core.robots["r1"].scans < n_live):
            time.sleep(0.2)
        node.stop()
        write_outputs(node.core, tmp_path / "replayed", node.summary())
    again = tmp_path / "replayed"
    assert node.core.robots["r1"].scans == n_live
    for f in ("trajectories/r1_online.csv", "trajectories/r1_final.csv",
              "maps/team-r1/map.png"):
        assert (again / f).read_bytes() == (live / "server" / f).read_bytes(), f
    assert yaml.safe_load((again / "maps/team-r1/map.yaml").read_text()) == \
        yaml.safe_load((live / "server/maps/team-r1/map.yaml").read_text())
