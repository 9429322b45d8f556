"""The daemons' log: plain dated lines on stderr that never wrap when it goes to a file, nothing
on stdout; `--help` shows no value type after flags; the yaw of a pose on the command line says
its unit."""

from __future__ import annotations

import logging
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mrslam.cli import app, log_level, setup_logging

DATED = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} (DEBUG|INFO|WARNING|ERROR|CRITICAL) ")


@pytest.fixture
def root_logging() -> Iterator[None]:
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    for h in [h for h in root.handlers if h not in handlers]:
        root.removeHandler(h)
    root.setLevel(level)


def test_a_daemon_writes_one_dated_line_per_line_and_never_wraps(
        root_logging: None, capsys: pytest.CaptureFixture[str]) -> None:
    setup_logging(0, "server", terminal=False)
    log = logging.getLogger("server.some.module")
    long = "a message longer than any terminal: " + "word " * 60
    log.info(long.strip())
    log.info("the lookout turns", extra={"robot_id": "r7"})
    log.warning("two lines:\nthe second one")
    try:
        raise ValueError("broken")
    except ValueError:
        log.exception("a failure")
    log.debug("not at the default level")
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert lines and all(DATED.match(line) for line in lines), lines
    assert lines[0].endswith(long.strip()) and " INFO    server.some.module: a message" in lines[0]
    assert lines[1].endswith("server.some.module [r7]: the lookout turns")
    assert lines[3].endswith("server.some.module: the second one")
    assert any(line.endswith("ValueError: broken") for line in lines[4:])
    assert not any("not at the default level" in line for line in lines)


def test_an_agent_names_its_robot_on_every_line(
        root_logging: None, capsys: pytest.CaptureFixture[str]) -> None:
    setup_logging(0, "agent", "r2", terminal=False)
    logging.getLogger("robot_agent.runtime").info("connected")
    (line,) = capsys.readouterr().err.splitlines()
    assert DATED.match(line) and line.endswith("robot_agent.runtime [r2]: connected")


def test_daemons_log_info_by_default_the_tools_warnings() -> None:
    for daemon in ("server", "agent", "sim"):
        assert log_level(daemon, 0) == log_level(daemon, 1) == logging.INFO
        assert log_level(daemon, 2) == logging.DEBUG
    assert log_level("slam-log", 0) == logging.WARNING
    assert log_level("slam-log", 1) == logging.INFO


def test_a_daemon_whose_stderr_is_a_file_logs_plain_lines_there(tmp_path: Path) -> None:
    """The real process, its stderr a file (as in the demo's run folder): a line of 200
    characters stays one line (Rich wrapped it at 80 columns), and stdout, kept for data, gets
    none of it."""
    err, out = tmp_path / "server.log", tmp_path / "stdout"
    code = ("import logging, sys; from mrslam.cli import setup_logging; "
            "setup_logging(0, 'server'); "
            "logging.getLogger('server.runtime.daemon').info('x' * 200)")
    with err.open("w") as f, out.open("w") as g:
        subprocess.run([sys.executable, "-c", code], stdout=g, stderr=f, check=True,
                       timeout=60)
    (line,) = err.read_text().splitlines()
    assert DATED.match(line) and line.endswith("server.runtime.daemon: " + "x" * 200)
    assert out.read_text() == ""


def test_help_shows_no_value_type_after_flags_and_the_yaw_unit() -> None:
    res = CliRunner().invoke(app, ["demo", "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0
    text = res.output
    assert "<bool>" not in text
    (verbose,) = [line for line in text.splitlines() if "--verbose" in line]
    assert "<int>" not in verbose
    assert "<float>" in text                         # options with values keep their type
    assert "yaw in radians" in text
    merge = CliRunner().invoke(app, ["merge", "--help"], env={"COLUMNS": "200"}).output
    assert "yaw in radians" in merge
    top = CliRunner().invoke(app, ["--help"], env={"COLUMNS": "200"}).output
    assert "--version" in top and "<bool>" not in top
