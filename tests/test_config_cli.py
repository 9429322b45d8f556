"""Config loading (YAML <- env <- overrides) and the CLI's contract."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
import yaml
from pydantic import BaseModel
from typer.testing import CliRunner

from mrslam import __version__
from mrslam.cli import app, call
from schemas.config import BusConfig
from schemas.config_loading import ConfigError, load_config, write_resolved


class Demo(BaseModel):
    robot_id: str = "r1"
    rate_hz: float = 10.0
    bus: BusConfig = BusConfig()


def test_yaml_env_and_overrides_in_order(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    f.write_text("robot_id: r2\nrate_hz: 5\nbus:\n  mode: client\n")
    env = {"MRSLAM_RATE_HZ": "7.5", "MRSLAM_BUS__CONNECT": '["tcp/10.0.0.2:7447"]',
           "MRSLAM_UNRELATED": "x", "OTHER": "y"}
    cfg = load_config(Demo, f, environ=env)
    assert (cfg.robot_id, cfg.rate_hz, cfg.bus.connect) == ("r2", 7.5, ["tcp/10.0.0.2:7447"])
    cfg = load_config(Demo, f, overrides={"rate_hz": 1.0}, environ=env)
    assert cfg.rate_hz == 1.0


def test_invalid_config_names_the_field(tmp_path: Path) -> None:
    f = tmp_path / "c.yaml"
    f.write_text("bus:\n  mode: satellite\n")
    with pytest.raises(ConfigError, match=r"bus\.mode"):
        load_config(Demo, f, environ={})
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(Demo, tmp_path / "missing.yaml", environ={})
    f.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(Demo, f, environ={})
    with pytest.raises(ConfigError, match="rate_hz"):
        load_config(Demo, None, environ={"MRSLAM_RATE_HZ": "fast"})


def test_resolved_config_round_trips(tmp_path: Path) -> None:
    cfg = load_config(Demo, None, overrides={"robot_id": "r3"}, environ={})
    path = write_resolved(cfg, tmp_path / "run")
    assert Demo.model_validate(yaml.safe_load(path.read_text())) == cfg


def test_version() -> None:
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and __version__ in res.output


def test_every_subcommand_exists() -> None:
    res = CliRunner().invoke(app, ["--help"])
    for cmd in ("server", "agent", "sim", "demo", "slam-log", "eval-relations", "world-map"):
        assert cmd in res.output


def test_help_shows_the_units_in_brackets() -> None:
    # help text writes units as [s], [ns], [m]: they must not be taken for markup and dropped
    res = CliRunner().invoke(app, ["replay", "--help"], env={"COLUMNS": "200"})
    assert "[ns]" in res.output and "[s]" in res.output
    res = CliRunner().invoke(app, ["eval-relations", "--help"], env={"COLUMNS": "200"})
    assert "[m]" in res.output and "[deg]" in res.output


def test_demo_with_a_value_out_of_range_says_which_and_exits_2() -> None:
    res = CliRunner().invoke(app, ["demo", "--coverage", "1.5"])
    assert res.exit_code == 2, res.output
    assert "coverage" in res.output and "less than or equal to 1" in res.output


def test_demo_takes_a_config_file_and_the_options_given_replace_its_keys(
        tmp_path: Path) -> None:
    """``mrslam demo --config FILE`` as every other command; each case fails before a run
    starts, in one line that shows which value won."""
    def demo(cfg: dict[str, object], *args: str) -> str:
        f = tmp_path / "demo.yaml"
        f.write_text(yaml.safe_dump(cfg))
        res = CliRunner().invoke(app, ["demo", "--config", str(f), *args])
        assert res.exit_code == 2, res.output
        assert len(res.output.strip().splitlines()) == 1, res.output
        return res.output

    assert "no scenario 'no-such-case'" in demo({"scenario": "no-such-case"})
    # an option on the command line replaces the file's key ...
    assert "'thesis-case-2' is called 'small-house-3' now" in demo(
        {"scenario": "no-such-case"}, "--scenario", "thesis-case-2")
    # ... and one left out does not put its default over the file's
    out = demo({"rtf": -1.0})
    assert "rtf" in out and "demo.yaml" in out
    # a world without a scenario runs without the default scenario's robots
    assert "no robots" in demo({"world": "sim/worlds/small_house.world"})


def test_unbuilt_command_exits_2_with_message(capsys: pytest.CaptureFixture[str]) -> None:
    def not_built() -> None:
        raise NotImplementedError

    with pytest.raises(typer.Exit) as ex:
        call("frobnicate", not_built)
    assert ex.value.exit_code == 2
    assert "frobnicate: not implemented yet" in capsys.readouterr().err


def test_expected_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    def bad() -> None:
        raise ConfigError("invalid Demo: bus.mode")

    with pytest.raises(typer.Exit) as ex:
        call("server", bad)
    assert ex.value.exit_code == 2 and "bus.mode" in capsys.readouterr().err
