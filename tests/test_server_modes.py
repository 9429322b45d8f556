"""The server's bus modes do what they say: ``--insecure`` and a partial ``bus:`` section give a
router, a second server on a busy port fails in one line, and the log names the endpoints the
router really listens on."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from bench.support.netsec import free_port, start_server, stop, wait_up
from schemas.config_loading import load_config
from server.config import ServerConfig
from tests.conftest import ROOT


def test_a_partial_bus_section_is_a_servers() -> None:
    insecure = load_config(ServerConfig, None, {"bus": {"insecure_listen": True}}, environ={})
    assert insecure.bus.mode == "router" and insecure.bus.connect == []
    assert insecure.bus.listen == ["tcp/0.0.0.0:7447"]    # what --insecure is for
    port = load_config(ServerConfig, None, {"bus": {"listen": ["tcp/127.0.0.1:9001"]}},
                       environ={})
    assert port.bus.mode == "router" and port.bus.listen == ["tcp/127.0.0.1:9001"]
    env = load_config(ServerConfig, None, None,
                      environ={"MRSLAM_BUS__LISTEN": '["tcp/127.0.0.1:9002"]'})
    assert env.bus.mode == "router" and env.bus.listen == ["tcp/127.0.0.1:9002"]
    client = load_config(ServerConfig, None, {"bus": {"mode": "client"}}, environ={})
    assert client.bus.connect == ["tcp/127.0.0.1:7447"]   # a worker connects where it did


@pytest.mark.e2e
def test_insecure_with_only_a_port_starts_a_router_and_says_where(tmp_path: Path) -> None:
    port = free_port()
    proc = start_server(tmp_path, {"listen": [f"tcp/127.0.0.1:{port}"]}, "--insecure",
                        extra={"out": str(tmp_path / "out")})
    try:
        with wait_up(f"tcp/127.0.0.1:{port}", proc):
            pass
    finally:
        assert stop(proc) == 0
    written = yaml.safe_load((tmp_path / "out" / "server_config.yaml").read_text())
    assert written["bus"]["mode"] == "router" and written["bus"]["insecure_listen"] is True
    log = (tmp_path / "server.log").read_text()
    assert f"router listening on tcp/127.0.0.1:{port}" in log


@pytest.mark.e2e
def test_a_second_server_on_a_busy_port_fails_in_one_line(tmp_path: Path) -> None:
    port = free_port()
    bus = {"listen": [f"tcp/127.0.0.1:{port}"]}
    first = start_server(tmp_path / "a", bus)
    try:
        wait_up(f"tcp/127.0.0.1:{port}", first).close()
        second = start_server(tmp_path / "b", bus)
        assert second.wait(timeout=60) == 2
        lines = (tmp_path / "b" / "server.log").read_text().strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in lines[0]
        assert f"127.0.0.1:{port}" in lines[0] and "in use" in lines[0]
    finally:
        stop(first)


@pytest.mark.e2e
@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
def test_the_log_names_the_tls_endpoint_of_the_servers_zenoh_file(tmp_path: Path) -> None:
    deploy = ROOT / "deploy" / "zenoh"
    certs = tmp_path / "certs"
    subprocess.run(["bash", str(deploy / "make-certs.sh"), str(certs), "127.0.0.1", "r1"],
                   check=True, capture_output=True)
    port = free_port()
    conf = subprocess.run([sys.executable, str(deploy / "config.py"), "server", "--certs",
                           str(certs), "--listen", f"tls/127.0.0.1:{port}", "r1"],
                          check=True, capture_output=True, text=True).stdout
    json.loads(conf)
    (tmp_path / "server.json5").write_text(conf)
    proc = start_server(tmp_path / "srv", {"zenoh_config": str(tmp_path / "server.json5")})
    try:
        log = tmp_path / "srv" / "server.log"
        t0 = time.monotonic()
        while "server up" not in log.read_text() and time.monotonic() - t0 < 60.0:
            assert proc.poll() is None, log.read_text()
            time.sleep(0.2)
        text = log.read_text()
        assert f"router listening on tls/127.0.0.1:{port}" in text
        assert "tcp/127.0.0.1:7447" not in text
    finally:
        stop(proc)
