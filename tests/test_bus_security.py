"""Secure by default (issue 20, item 4): the server listens on loopback unless TLS and access
rules are configured, or an insecure listen is asked for explicitly and warned about."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.support.netsec import ROOT, connect, free_port, primary_ip, start_server, stop, wait_up
from schemas.bus import is_loopback_endpoint, listen_security, zenoh_config
from schemas.config import BusConfig
from schemas.config_loading import ConfigError, load_config
from server.config import ServerConfig

HOST = primary_ip()
needs_address = pytest.mark.skipif(HOST is None, reason="this machine has no address but "
                                   "loopback")


@pytest.mark.parametrize(("endpoint", "local"), [
    ("tcp/127.0.0.1:7447", True), ("tcp/127.3.2.1:1", True), ("tcp/[::1]:7447", True),
    ("tcp/localhost:7447", True), ("unixsock-stream//tmp/z.sock", True),
    ("tcp/0.0.0.0:7447", False), ("tcp/[::]:7447", False), ("tcp/192.0.2.2:7447", False),
    ("tls/server.lab.local:7447", False), ("udp/10.0.0.1:7447?iface=eth0", False),
])
def test_loopback_endpoints(endpoint: str, local: bool) -> None:
    assert is_loopback_endpoint(endpoint) is local


def secured_file(tmp_path: Path, *, mtls: bool = True, acl: bool = True,
                 listen: str = "tls/0.0.0.0:7447") -> str:
    conf = {"mode": "router", "listen": {"endpoints": [listen]},
            "transport": {"link": {"tls": {"root_ca_certificate": "/certs/ca.pem",
                                           "listen_certificate": "/certs/server.pem",
                                           "listen_private_key": "/certs/server.key",
                                           "enable_mtls": mtls}}},
            "access_control": {"enabled": acl, "default_permission": "deny"}}
    path = tmp_path / "zenoh.json5"
    path.write_text(json.dumps(conf))
    return str(path)


def test_what_an_exposed_listener_lacks(tmp_path: Path) -> None:
    sec = listen_security(zenoh_config("router", ["tcp/0.0.0.0:7447"]))
    assert sec.exposed == ["tcp/0.0.0.0:7447"] and len(sec.missing) == 2
    assert "TLS" in sec.missing[0] and "access control" in sec.missing[1]
    # a router without endpoints of its own listens where Zenoh's defaults say: everywhere
    assert listen_security(zenoh_config("router")).exposed == ["tcp/[::]:7447"]
    assert listen_security(zenoh_config("client", connect=["tcp/10.0.0.1:7447"])).secure
    assert listen_security(zenoh_config("router", ["tcp/127.0.0.1:7447"])).secure
    assert listen_security(zenoh_config("router", config_file=secured_file(tmp_path))).secure
    no_mtls = listen_security(zenoh_config(
        "router", config_file=secured_file(tmp_path, mtls=False)))
    assert no_mtls.missing == ["client certificates (transport.link.tls.enable_mtls)"]
    no_acl = listen_security(zenoh_config("router", config_file=secured_file(tmp_path,
                                                                             acl=False)))
    assert no_acl.missing == ["access control (access_control.enabled)"]
    # TLS in the file, but our own plain-TCP endpoint on top of it
    mixed = listen_security(zenoh_config("router", ["tcp/0.0.0.0:7447"],
                                         config_file=secured_file(tmp_path)))
    assert mixed.missing == ["TLS (not on tcp/0.0.0.0:7447)"]


def test_the_default_server_listens_on_loopback_only() -> None:
    assert ServerConfig().bus.listen == ["tcp/127.0.0.1:7447"]


def test_an_exposed_listener_needs_tls_and_access_rules_or_the_insecure_option(
        tmp_path: Path) -> None:
    f = tmp_path / "server.yaml"
    f.write_text("bus: {mode: router, listen: [tcp/0.0.0.0:7447], connect: []}\n")
    with pytest.raises(ConfigError, match=r"bus: would listen on tcp/0\.0\.0\.0:7447 without "
                       r"TLS.*insecure_listen: true") as e:
        load_config(ServerConfig, f, environ={})
    assert "\n" not in str(e.value)
    f.write_text("bus: {mode: router, listen: [], connect: []}\n")   # Zenoh's default: all
    with pytest.raises(ConfigError, match=r"tcp/\[::\]:7447"):
        load_config(ServerConfig, f, environ={})
    cfg = load_config(ServerConfig, f, {"bus": {"insecure_listen": True}}, environ={})
    assert cfg.bus.insecure_listen
    ok = BusConfig(mode="router", listen=[], zenoh_config=secured_file(tmp_path))
    assert ok.zenoh_config is not None


@needs_address
@pytest.mark.e2e
def test_a_client_on_another_address_cannot_reach_a_default_server(tmp_path: Path) -> None:
    port = free_port()
    # the default bus but for the port (7447 may be in use on a shared machine)
    proc = start_server(tmp_path, {**ServerConfig().bus.model_dump(),
                                   "listen": [f"tcp/127.0.0.1:{port}"]})
    try:
        with wait_up(f"tcp/127.0.0.1:{port}", proc):
            stranger = connect(f"tcp/{HOST}:{port}")
            assert stranger is None, f"reached the server on {HOST}"
    finally:
        stop(proc)


@needs_address
@pytest.mark.e2e
def test_a_server_refuses_an_exposed_listener_unless_told_it_is_insecure(
        tmp_path: Path) -> None:
    port = free_port()
    bus = {"mode": "router", "listen": [f"tcp/0.0.0.0:{port}"], "connect": []}
    proc = start_server(tmp_path / "refused", bus)
    assert proc.wait(timeout=60) == 2
    lines = (tmp_path / "refused" / "server.log").read_text().strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in lines[0]
    assert "without TLS" in lines[0] and "--insecure" in lines[0]
    proc = start_server(tmp_path / "insecure", bus, "--insecure")
    try:
        with wait_up(f"tcp/127.0.0.1:{port}", proc):
            stranger = connect(f"tcp/{HOST}:{port}")
            assert stranger is not None   # what the option allows ...
            stranger.close()
    finally:
        stop(proc)
    log = (tmp_path / "insecure" / "server.log").read_text()
    assert "WARNING" in log and "without TLS" in log   # ... said at start


@pytest.mark.e2e
def test_the_deploy_server_config_counts_as_secured(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, str(ROOT / "deploy" / "zenoh" / "config.py"), "server",
                          "--certs", str(tmp_path), "--listen", "tls/0.0.0.0:7447", "r1"],
                         check=True, capture_output=True, text=True).stdout
    (tmp_path / "server.json5").write_text(out)
    # as deploy/README.md has it: listen: [] takes the file's endpoints
    cfg = BusConfig(mode="router", listen=[], connect=[],
                    zenoh_config=str(tmp_path / "server.json5"))
    sec = listen_security(zenoh_config("router", config_file=cfg.zenoh_config))
    assert sec.exposed == ["tls/0.0.0.0:7447"] and sec.secure
