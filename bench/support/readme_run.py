"""The demo run the README shows: its figures, its caption and its sample output.

``docs/img/demo-run.json`` holds what the README quotes of one run of the default demo (lockstep,
so the same code gives the same run): who joined whom and when, when the threshold was
reached, the console's output, and the hash of ``docs/img/merged-map.png`` drawn in that run.
The README's caption and sample output are made from it (between the ``demo-run`` markers), and
``python bench/readme.py --write`` makes all three again from a fresh run. Tests check that the
README says what the file says, and that a fresh run still gives the file's figures.
"""

from __future__ import annotations

import hashlib
import re
import textwrap
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
REFERENCE = ROOT / "docs" / "img" / "demo-run.json"
MAP_PNG = ROOT / "docs" / "img" / "merged-map.png"
README = ROOT / "README.md"

def begin(part: str) -> str:
    return (f"<!-- demo-run {part}: made from docs/img/demo-run.json by "
            "`python bench/readme.py --write` -->")


def end(part: str) -> str:
    return f"<!-- /demo-run {part} -->"


#: how a merge came about, as the caption says it
HOW = {"tags": "on tag sightings", "map": "on the maps alone", "start": "from known starts",
       "meeting": "at a planned meeting"}
NUMBERS = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six"}


def figures(report: dict[str, Any]) -> dict[str, Any]:
    """What the README quotes of a run, from its ``report.json``: the parts a lockstep run
    repeats (who joined whom, when and how, when the threshold was reached, how it ended)."""
    joins = []
    for m in report["merges"]:
        if m.get("undone"):
            continue
        joined = list(report["teams"].get(m["joined_team_id"], {}).get("robot_ids", []))
        joins.append({"sim_time_s": m["sim_time_s"], "kind": m["kind"], "robots": joined,
                      "into": [r for r in m["robots"] if r not in joined]})
    final = [t for t in report["teams"].values() if not t.get("merged_into")]
    return {"scenario": report["scenario"], "seed": report["seed"],
            "lockstep": report["lockstep"], "robots": len(report["robots_spawn"]),
            "threshold": report["threshold"], "reached": report["reached"],
            "sim_time_to_threshold_s": report["sim_time_to_threshold_s"],
            "end": report["end"], "joins": joins, "final_teams": len(final)}


def caption(fig: dict[str, Any]) -> str:
    """The figure's caption, wrapped as the README is."""
    said: list[str] = []
    for j in fig["joins"]:
        whom = "+".join(j["into"]) if not said else "them"
        said.append(f"{'+'.join(j['robots'])} joined {whom} at {j['sim_time_s']:.1f} s "
                    f"{HOW.get(j['kind'], 'by ' + j['kind'])}")
    n = NUMBERS.get(fig["robots"], str(fig["robots"]))
    end = ("end as one team with one map" if fig["final_teams"] == 1
           else f"end as {fig['final_teams']} teams")
    reached = (f"{fig['threshold']:.0%} covered after {fig['sim_time_to_threshold_s']:.0f} s "
               "of simulated time" if fig["reached"] else "the threshold not reached")
    text = (f"*`make demo`: {n} robots start apart in a 20 × 20 m house, explore alone, meet, "
            f"and {end} ({', '.join(said)}; {reached}). Lines are the robots' trajectories in "
            "the merged map's frame.*")
    return textwrap.fill(text.replace("%", " %"), width=96, break_on_hyphens=False)


def sample_output(console_text: str, run_folder: str) -> str:
    """The demo's console output as the README shows it: the run folder's date and time as
    placeholders, log lines left out."""
    out = []
    for line in console_text.splitlines():
        if re.match(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", line):
            continue
        out.append(line.rstrip().replace(run_folder, re.sub(
            r"-\d{8}-\d{6}$", "-<date>-<time>", run_folder)))
    return "\n".join(out).strip("\n")


def sections(ref: dict[str, Any]) -> dict[str, str]:
    """What stands between each part's markers in the README."""
    return {"caption": f"{begin('caption')}\n{caption(ref['figures'])}\n{end('caption')}",
            "output": f"{begin('output')}\n```text\n{ref['output']}\n```\n{end('output')}"}


def marked(readme: str, part: str) -> str:
    """The README's text from ``part``'s first marker to its last."""
    start = readme.index(begin(part))
    return readme[start:readme.index(end(part), start) + len(end(part))]


def splice(readme: str, ref: dict[str, Any]) -> str:
    """``readme`` with each marked part made again from ``ref``."""
    for part, text in sections(ref).items():
        readme = readme.replace(marked(readme, part), text)
    return readme


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
