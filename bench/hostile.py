"""mrslam as a hostile world treats it: each section attacks one promise and prints its figures.

Sections (``--only NAME ...`` runs some of them; all by default), each a function returning a
dict with its measurements and ``goal_met``:

- ``payloads``, ``payloads_uncapped``, ``stranger``, ``bad_inputs``: the bus, the robots'
  commands and the command line (``bench/hostile_bus.py`` says what each does).
- ``fake_ids``, ``newcomer_flood``, ``clocks``: the server's admission and its clocks
  (``bench/hostile_fleet.py``).
- ``full_disk``: the state folder on a disk that fills up (``bench/hostile_disk.py``).
- ``stop_demo``, ``stop_server``: signals to the demo and the server from outside; is every
  process of the run gone 5 s later, and the report written (``bench/hostile_stop.py``)?

The whole result is printed as one JSON object, ``{section: {...}}``.

    python bench/hostile.py [--only SECTION ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

Section = Callable[[Path], dict[str, Any]]

#: name -> section; each takes a scratch folder of its own
SECTIONS: dict[str, Section] = {}

from hostile_bus import SECTIONS as BUS_SECTIONS  # noqa: E402  (payloads, stranger, bad_inputs)
from hostile_disk import SECTIONS as DISK_SECTIONS  # noqa: E402  (full_disk)
from hostile_fleet import SECTIONS as FLEET_SECTIONS  # noqa: E402  (fake_ids, clocks)
from hostile_stop import SECTIONS as STOP_SECTIONS  # noqa: E402  (stop_demo, stop_server)

SECTIONS.update(BUS_SECTIONS)
SECTIONS.update(FLEET_SECTIONS)
SECTIONS.update(DISK_SECTIONS)
SECTIONS.update(STOP_SECTIONS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=sorted(SECTIONS), default=None)
    ap.add_argument("--out", type=Path, default=None, help="keep scratch folders here")
    args = ap.parse_args()
    names = args.only or list(SECTIONS)
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        base = args.out or Path(tmp)
        for name in names:
            folder = base / name
            folder.mkdir(parents=True, exist_ok=True)
            results[name] = SECTIONS[name](folder)
            print(f"{name}: {json.dumps(results[name])}", file=sys.stderr)
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
