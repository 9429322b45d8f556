"""The files a Zenoh config's TLS section names, checked before a session opens.

Zenoh reads the CA, certificate and key only when a link is made: a mistyped path in a
client's config shows as "Unable to connect … Timeout!", and in a router's as "Invalid TLS
certificate file: No such file or directory" without the file. Each setting here is read
first, so the error names the setting and the file.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: the settings under ``transport/link/tls`` that hold a file's path
TLS_FILE_KEYS = ("root_ca_certificate", "listen_certificate", "listen_private_key",
                 "connect_certificate", "connect_private_key")


def tls_file_problems(conf: Any) -> list[str]:
    """``transport.link.tls.<key>: <path>: <problem>`` for every file the ``zenoh.Config``
    ``conf`` names that cannot be read (relative paths from the working folder, as Zenoh
    reads them); empty when all can."""
    try:
        tls = json.loads(conf.get_json("transport/link/tls")) or {}
    except Exception:   # a Zenoh without that section: nothing to check
        return []
    problems = []
    for key in TLS_FILE_KEYS:
        path = tls.get(key)
        if not isinstance(path, str) or not path:
            continue
        problem = _unreadable(Path(path))
        if problem:
            problems.append(f"transport.link.tls.{key}: {path}: {problem}")
    return problems


def _unreadable(path: Path) -> str | None:
    try:
        with path.open("rb") as f:
            if not f.read(1):
                return "empty file"
    except FileNotFoundError:
        return "no such file"
    except IsADirectoryError:
        return "a folder, not a file"
    except OSError as e:
        return e.strerror or str(e)
    return None
