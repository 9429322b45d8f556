"""Every command, every bad input it takes: exit code 2 and one line on stderr naming the
problem, never a traceback (issue 20, item 6). Runs the real CLI as a process."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.support.bad_inputs import BadInput, cases, run, write_files

CASES = cases(Path("/FOLDER"))


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bad")
    write_files(out)
    return out


@pytest.mark.e2e
@pytest.mark.parametrize("index", range(len(CASES)), ids=[c.id for c in CASES])
def test_a_bad_input_is_one_line_and_exit_2(folder: Path, index: int) -> None:
    case: BadInput = cases(folder)[index]
    out = run(case)
    assert out.code == 2, out
    assert len(out.stderr_lines) == 1, out.stderr_lines
    line = out.stderr_lines[0]
    assert "Traceback" not in line and ".rs:" not in line
    assert line.startswith(f"mrslam: {case.command}: ") and case.says in line, line


def test_every_command_with_inputs_is_covered() -> None:
    covered = {c.command for c in CASES}
    assert covered >= {"server", "agent", "sim", "demo", "world-map", "slam-log",
                       "eval-relations", "record", "replay", "merge", "lidar-dump"}
