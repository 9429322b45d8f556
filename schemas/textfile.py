"""Reading a YAML file someone handed us, whatever it turns out to hold.

A config, a nav2 map's ``.yaml`` or a scenarios file may be missing, a folder, unreadable,
binary, cut short or nested beyond reason. ``read_yaml`` gives back what the file holds, or
raises ``UnreadableFile`` whose message is ``<path>: <the problem>`` on one line; each reader
turns it into its own typed error (``ConfigError``, ``WorldError``, …).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml


class UnreadableFile(ValueError):
    """A file that cannot be read as YAML text; the message names the file and the problem.
    ``problem`` is the message without the file."""

    user_error = True

    def __init__(self, path: Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


def read_text(path: Path, what: str = "text") -> str:
    """The file's text (UTF-8); ``what`` names what it should hold ("a config is YAML
    text")."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UnreadableFile(path, f"cannot read ({e.strerror or e})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UnreadableFile(path, f"not a text file (byte {e.start} is not UTF-8); {what}"
                             ) from None


def read_yaml(path: Path, what: str = "the file is YAML text") -> Any:
    """The document in a YAML file (None for an empty one)."""
    text = read_text(path, what)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UnreadableFile(path, f"not valid YAML ({yaml_problem(e)})") from None
    except RecursionError:   # "[[[[…": PyYAML's parser recurses once per level
        raise UnreadableFile(path, "not valid YAML (nested too deeply)") from None


def yaml_problem(err: yaml.YAMLError) -> str:
    """The YAML error in one line: what is wrong and where."""
    if isinstance(err, yaml.MarkedYAMLError) and err.problem:
        mark = err.problem_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        return f"{err.problem}{where}"
    return " ".join(str(err).split())
