"""deploy/: the setup script parses, the units run the right commands, the sketch speaks the
driver's protocol."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from robot_agent.drivers import base_protocol as proto
from tests.conftest import ROOT

DEPLOY = ROOT / "deploy"


def test_pi_setup_is_valid_bash() -> None:
    subprocess.run(["bash", "-n", str(DEPLOY / "pi-setup.sh")], check=True)


@pytest.mark.parametrize("unit, command", [("mrslam-server.service", "mrslam server -c"),
                                           ("mrslam-agent.service", "mrslam agent -c")])
def test_units_start_the_daemons(unit: str, command: str) -> None:
    text = (DEPLOY / "systemd" / unit).read_text()
    exec_start = re.search(r"^ExecStart=(.*)$", text, re.M)
    assert exec_start and command in exec_start.group(1)
    assert "KillSignal=SIGTERM" in text and "WantedBy=multi-user.target" in text
    if shutil.which("systemd-analyze"):
        out = subprocess.run(["systemd-analyze", "verify", str(DEPLOY / "systemd" / unit)],
                             capture_output=True, text=True)
        # the venv does not exist here; anything else is an error in the unit
        problems = [line for line in out.stderr.splitlines()
                    if line.strip() and "is not executable" not in line]
        assert problems == []


def test_the_sketch_uses_the_drivers_constants() -> None:
    ino = (DEPLOY / "firmware" / "base" / "base.ino").read_text()
    consts = dict(re.findall(r"(T_SPEED|T_STOP|T_ENCODERS) = (0x[0-9A-Fa-f]+)", ino))
    assert {k: int(v, 16) for k, v in consts.items()} == {
        "T_SPEED": proto.SPEED, "T_STOP": proto.STOP, "T_ENCODERS": proto.ENCODERS}
    assert "0x07" in ino and "0xAA" in ino and "0x55" in ino
    assert f"uint8_t f[6 + {len(proto.Encoders(0, 0, 0, 0).encode(0)) - 6}]" in ino


def test_the_agent_config_pi_setup_writes_is_valid() -> None:
    import yaml

    from robot_agent.config import AgentConfig

    script = (DEPLOY / "pi-setup.sh").read_text()
    body = re.search(r"<<YAML\n(.*?)\nYAML\n", script, re.S)
    assert body is not None
    text = (body.group(1).replace("$rid", "r1").replace("$endpoint", "tls/server:7447")
            .replace("$zenoh_config", "/etc/mrslam/zenoh-agent.json5"))
    cfg = AgentConfig.model_validate(yaml.safe_load(text))
    assert cfg.robot_id == "r1" and cfg.detector.body_radius_m > 0
