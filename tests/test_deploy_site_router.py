"""Several sites: a site router (zenohd's config, run here as a Python router session with the
same json5 file) between remote robots and the server, over mutual TLS, with access control."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest

from schemas import Scan, VelocityCommand, keys
from schemas.bus import Bus, free_local_endpoint
from tests.conftest import ROOT
from tests.examples import scan
from tests.test_deploy_zenoh import stream_arrives, wait_for, write_config

DEPLOY = ROOT / "deploy"
#: runs the deploy scripts and starts processes on them: the e2e tier
pytestmark = [pytest.mark.e2e,
              pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")]


def test_robots_behind_a_site_router_reach_the_server_only_under_their_keys(
        tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(DEPLOY / "zenoh" / "make-certs.sh"), str(certs), "127.0.0.1",
                    "r1", "r3", "r4", "site-b"], check=True, capture_output=True)
    central = free_local_endpoint().replace("tcp/", "tls/")
    site = free_local_endpoint().replace("tcp/", "tls/")
    server_conf = write_config(tmp_path, "server", "server", "--certs", str(certs),
                               "--listen", central, "--site", "site-b=r3,r4", "r1")
    site_conf = write_config(tmp_path, "site-b", "zenohd", "--certs", str(certs), "--name",
                             "site-b", "--listen", site, "--connect", central, "r3", "r4")
    got: list[str] = []
    seqs: set[int] = set()
    with Bus.open("router", config_file=server_conf) as server, \
            Bus.open("router", config_file=site_conf) as _site:

        def on_scan(key: str, msg: Scan) -> None:
            got.append(key)
            seqs.add(msg.seq)

        server.subscribe(keys.ALL_SCANS, Scan, on_scan)
        r3 = Bus.open("client", config_file=write_config(
            tmp_path, "r3", "agent", "--certs", str(certs), "--connect", site, "--robot", "r3"),
            connect_timeout_ms=3000)
        try:
            cmds: list[VelocityCommand] = []
            r3.subscribe(keys.robot_cmd_vel("r3"), VelocityCommand, lambda k, m: cmds.append(m))
            # routes through the site router take a moment to form (longer on a busy
            # machine): send again until something arrives, the refused keys every time too
            deadline = time.monotonic() + 15.0
            seq = 0
            while not (got and cmds) and time.monotonic() < deadline:
                seq += 3
                r3.publish(keys.robot_scan("r1"), scan("r1", seq=seq), block=True)  # refused
                r3.publish(keys.robot_scan("r4"), scan("r4", seq=seq + 1), block=True)  # refused
                r3.publish(keys.robot_scan("r3"), scan("r3", seq=seq + 2), block=True)
                server.publish(keys.robot_cmd_vel("r3"), VelocityCommand(
                    robot_id="r3", v_mps=0.1, omega_rps=0.0), block=True)
                wait_for(lambda: bool(got and cmds), 0.5)
            assert got and cmds, (got, cmds)
            time.sleep(0.5)
            assert set(got) == {"mrslam/robot/r3/scan"}
            assert {c.robot_id for c in cmds} == {"r3"}
            assert stream_arrives(r3, "r3", 5000, lambda: set(seqs))  # every scan, not one
        finally:
            r3.close()
