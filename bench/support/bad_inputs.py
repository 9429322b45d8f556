"""Bad inputs for every ``mrslam`` command that takes them (issue 20, item 6), shared by the
test that runs them and the ``bad_inputs`` section of ``bench/hostile.py``.

Each must end the command with exit code 2 and one line on stderr naming the problem.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WORLD = ROOT / "sim" / "worlds" / "small_house.world"
#: a path under an existing file: nothing can be written there
UNDER_A_FILE = "/etc/passwd/x"
#: a TCP port nobody listens on (the discard port: reserved, never served here)
CLOSED = "tcp/127.0.0.1:9"
OPEN_LISTEN = "tcp/0.0.0.0:7"
CLOSED_TLS = "tls/127.0.0.1:9"


@dataclass(frozen=True)
class BadInput:
    command: str
    problem: str
    args: tuple[str, ...]       # after ``mrslam``
    says: str                   # the stderr line names the problem with this

    @property
    def id(self) -> str:
        return f"{self.command}-{self.problem}"


def write_files(folder: Path) -> None:
    """The bad files the cases refer to."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "binary.yaml").write_bytes(bytes(range(256)) * 8)
    (folder / "image.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(64))
    (folder / "missing-zenoh.yaml").write_text(f"bus: {{zenoh_config: {folder}/none.json5}}\n")
    (folder / "bad.json5").write_text("{ mode: 'router', listen: [ \n")
    (folder / "bad-zenoh.yaml").write_text(f"bus: {{zenoh_config: {folder}/bad.json5}}\n")
    (folder / "bad-field.yaml").write_text("bus: {mode: satellite}\n")
    (folder / "open.yaml").write_text(f"bus: {{mode: router, listen: [{OPEN_LISTEN}]}}\n")
    (folder / "nan-start.yaml").write_text("teams: {start_poses: {r1: [0, .nan, 0]}}\n")
    (folder / "deep.yaml").write_text("[" * 100_000)
    _bad_maps(folder)
    _mistyped_certificates(folder)
    _known_maps(folder)
    earlier = folder / "earlier-run" / "server" / "state"   # a run's folder, used again
    earlier.mkdir(parents=True, exist_ok=True)
    (earlier / "journal-0001.mcap").write_bytes(b"\x00" * 16)


def _known_maps(folder: Path) -> None:
    """A known_map folder of a format version this release does not read (``--map``)."""
    newer = folder / "newer-map"
    newer.mkdir(exist_ok=True)
    (newer / "map.json").write_text(json.dumps({"format": "mrslam-known-map", "version": 99}))


def _mistyped_certificates(folder: Path) -> None:
    """TLS configs whose key (a robot's) or certificate (the server's) is mistyped."""
    for name in ("ca.pem", "r1.pem", "r1.key", "server.pem", "server.key"):
        (folder / name).write_text("-----BEGIN CERTIFICATE-----\n")   # never read by Zenoh
    tls = {"root_ca_certificate": f"{folder}/ca.pem", "enable_mtls": True}
    robot = {**tls, "connect_certificate": f"{folder}/r1.pem",
             "connect_private_key": f"{folder}/r1.kye"}
    server = {**tls, "listen_certificate": f"{folder}/sever.pem",
              "listen_private_key": f"{folder}/server.key"}
    for name, block in (("tls-robot", robot), ("tls-server", server)):
        (folder / f"{name}.json5").write_text(
            json.dumps({"transport": {"link": {"tls": block}}}, indent=2))
    (folder / "tls-robot.yaml").write_text(
        f"bus: {{zenoh_config: {folder}/tls-robot.json5, connect: [{CLOSED_TLS}], "
        "connect_timeout_ms: 2000}\n")
    (folder / "tls-server.yaml").write_text(
        f"bus: {{mode: router, zenoh_config: {folder}/tls-server.json5, "
        f"listen: [{CLOSED_TLS}]}}\n")


#: bad nav2 maps (``map-<problem>.yaml``) -> what the one line says of each
BAD_MAPS = {
    "random": "map-random.yaml: not a text file",
    "empty": "map-empty.yaml: is empty",
    "truncated": "map-truncated.yaml: not valid YAML",
    "no-image": "image 'none.pgm' not found",
    "not-an-image": "image 'notes.pgm' is not an image",
    "unreadable-image": "image 'unreadable.pgm': cannot read (Permission denied)",
    "folder": "map-folder.yaml: cannot read (Is a directory)",
    "unreadable": "map-unreadable.yaml",
    "deep": "map-deep.yaml: not valid YAML (nested too deeply)",
    "far": "map-far.yaml: origin",
}


def _bad_maps(folder: Path) -> None:
    def meta(image: str, origin: str = "[0, 0, 0]") -> str:
        return f"image: {image}\nresolution: 0.05\norigin: {origin}\n"

    (folder / "map-random.yaml").write_bytes(random.Random(42).randbytes(4096))
    (folder / "map-empty.yaml").write_bytes(b"")
    (folder / "map-truncated.yaml").write_text(meta("map.pgm")[:-6])
    (folder / "map-no-image.yaml").write_text(meta("none.pgm"))
    (folder / "notes.pgm").write_text("not a picture\n")
    (folder / "map-not-an-image.yaml").write_text(meta("notes.pgm"))
    _unreadable(folder / "unreadable.pgm")
    (folder / "map-unreadable-image.yaml").write_text(meta("unreadable.pgm"))
    (folder / "map-folder.yaml").mkdir(exist_ok=True)
    _unreadable(folder / "map-unreadable.yaml")
    (folder / "map-deep.yaml").write_text("[" * 100_000)
    (folder / "map-far.yaml").write_text(meta("notes.pgm", "[1.0e+300, 0, 0]"))


#: a file that reading fails on with "Permission denied" even for root (write-only)
WRITE_ONLY = Path("/proc/sys/vm/drop_caches")


def _unreadable(path: Path) -> None:
    """A file nobody may read: mode 000, or for root (who reads anything) a link to a
    write-only kernel file."""
    if path.is_symlink() or path.exists():
        path.unlink()
    if os.geteuid() == 0:
        path.symlink_to(WRITE_ONLY)
    else:
        path.write_text("secret\n")
        path.chmod(0)


def cases(folder: Path) -> list[BadInput]:
    """Every bad input × every command that takes it (files from ``write_files(folder)``)."""
    f = str(folder)
    out: list[BadInput] = []
    with_config = {"server": (), "agent": (), "sim": (),
                   "slam-log": (str(folder / "none.clf"), "--out", f"{f}/out"),
                   "merge": (str(folder / "a.mcap"), str(folder / "b.mcap"), "--out",
                             f"{f}/out")}
    for cmd, rest in with_config.items():
        out += [
            BadInput(cmd, "binary-config", (cmd, *rest, "-c", f"{f}/binary.yaml"),
                     "not a text file"),
            BadInput(cmd, "png-config", (cmd, *rest, "-c", f"{f}/image.png"),
                     "not a text file"),
            BadInput(cmd, "invalid-field", (cmd, *rest, "-c", f"{f}/bad-field.yaml"),
                     "bus: Extra inputs" if cmd == "slam-log"    # it has no bus
                     else "bus.mode: Input should be"),
        ]
    sim = ("--world", str(WORLD), "--robot", "r1:0,0,0")
    for cmd, rest in (("server", ()), ("agent", ()), ("sim", sim)):
        out += [
            BadInput(cmd, "missing-zenoh-config", (cmd, *rest, "-c", f"{f}/missing-zenoh.yaml"),
                     "none.json5: No such file"),
            BadInput(cmd, "invalid-zenoh-config", (cmd, *rest, "-c", f"{f}/bad-zenoh.yaml"),
                     "bad.json5: expected"),
        ]
    for cmd, rest in (("record", ("--out", f"{f}/r.mcap")), ("replay", (f"{f}/a.mcap",))):
        out += [
            BadInput(cmd, "missing-zenoh-config",
                     (cmd, *rest, "--zenoh-config", f"{f}/none.json5"),
                     "none.json5: No such file"),
            BadInput(cmd, "invalid-zenoh-config",
                     (cmd, *rest, "--zenoh-config", f"{f}/bad.json5"), "bad.json5: expected"),
        ]
    for problem, says in BAD_MAPS.items():
        world = f"{f}/map-{problem}.yaml"
        out += [BadInput("world-map", f"map-{problem}", ("world-map", world, "--out", f"{f}/wm"),
                         says),
                BadInput("demo", f"map-{problem}", ("demo", "--world", world, "--robot", "r1:0,0",
                                                    "--out", f"{f}/demo"), says)]
    out += [
        BadInput("sim", "map-random", ("sim", "--world", f"{f}/map-random.yaml", "--robot",
                                       "r1:0,0"), BAD_MAPS["random"]),
        BadInput("server", "deep-config", ("server", "-c", f"{f}/deep.yaml"),
                 "deep.yaml: not valid YAML (nested too deeply)"),
        BadInput("agent", "mistyped-key", ("agent", "-c", f"{f}/tls-robot.yaml"),
                 "transport.link.tls.connect_private_key: /FOLDER/r1.kye: no such file"
                 .replace("/FOLDER", f)),
        BadInput("record", "mistyped-key", ("record", "--out", f"{f}/r.mcap", "--zenoh-config",
                                            f"{f}/tls-robot.json5", "--connect", CLOSED_TLS),
                 f"{f}/r1.kye: no such file"),
        BadInput("server", "mistyped-certificate", ("server", "-c", f"{f}/tls-server.yaml"),
                 f"transport.link.tls.listen_certificate: {f}/sever.pem: no such file"),
        BadInput("sim", "out-under-a-file", ("sim", "--world", str(WORLD), "--out",
                                             UNDER_A_FILE), "/etc/passwd is a file"),
        BadInput("demo", "out-under-a-file", ("demo", "--out", UNDER_A_FILE),
                 "/etc/passwd is a file"),
        BadInput("demo", "out-holds-a-run", ("demo", "--out", f"{f}/earlier-run"),
                 f"{f}/earlier-run already holds a run ({f}/earlier-run/server/state is not "
                 "empty)"),
        BadInput("world-map", "out-under-a-file", ("world-map", str(WORLD), "--out",
                                                   UNDER_A_FILE), "/etc/passwd is a file"),
        BadInput("slam-log", "out-under-a-file", ("slam-log", f"{f}/none.clf", "--out",
                                                  UNDER_A_FILE), "/etc/passwd is a file"),
        BadInput("merge", "out-under-a-file", ("merge", f"{f}/a.mcap", f"{f}/b.mcap", "--out",
                                               UNDER_A_FILE), "/etc/passwd is a file"),
        BadInput("record", "out-under-a-file", ("record", "--out", f"{UNDER_A_FILE}.mcap"),
                 "/etc/passwd is a file"),
        BadInput("world-map", "resolution-0", ("world-map", str(WORLD), "--out", f"{f}/wm",
                                               "--resolution", "0"), "--resolution"),
        BadInput("world-map", "resolution-nan", ("world-map", str(WORLD), "--out", f"{f}/wm",
                                                 "--resolution", "nan"), "--resolution"),
        BadInput("world-map", "resolution-text", ("world-map", str(WORLD), "--out", f"{f}/wm",
                                                  "--resolution", "fine"), "--resolution"),
        BadInput("agent", "unreachable-router", ("agent", "--connect", CLOSED),
                 "Unable to connect"),
        BadInput("agent", "malformed-endpoint", ("agent", "--connect", "nowhere"),
                 "Endpoints must be of the form"),
        BadInput("record", "unreachable-router", ("record", "--out", f"{f}/r.mcap",
                                                  "--connect", CLOSED), "Unable to connect"),
        BadInput("server", "insecure-listen", ("server", "-c", f"{f}/open.yaml"),
                 "without TLS"),
        BadInput("server", "nan-start-pose", ("server", "-c", f"{f}/nan-start.yaml"),
                 "teams.start_poses.r1.1: Input should be a finite number"),
        BadInput("sim", "insecure-listen", ("sim", "--world", str(WORLD), "--listen",
                                            OPEN_LISTEN), "without TLS"),
        BadInput("record", "insecure-listen", ("record", "--out", f"{f}/r.mcap", "--listen",
                                               OPEN_LISTEN), "without TLS"),
        BadInput("eval-relations", "binary-files", ("eval-relations", f"{f}/binary.yaml",
                                                    f"{f}/image.png"), "binary.yaml"),
        BadInput("server", "map-missing", ("server", "--map", f"{f}/no-map"), "no such folder"),
        BadInput("server", "map-newer", ("server", "--map", f"{f}/newer-map"),
                 "a map of format version 99; this release reads version 1"),
        BadInput("demo", "map-not-a-folder", ("demo", "--map", f"{f}/binary.yaml", "--out",
                                              f"{f}/demo"), "not a folder"),
        BadInput("demo", "map-newer", ("demo", "--map", f"{f}/newer-map", "--out",
                                       f"{f}/demo"), "format version 99"),
        BadInput("lidar-dump", "missing-port", ("lidar-dump", "--port", f"{f}/no-tty",
                                                "--timeout", "1"), "no-tty"),
    ]
    return out


@dataclass(frozen=True)
class Outcome:
    code: int
    stderr_lines: list[str]

    def one_line_naming(self, says: str) -> bool:
        return (self.code == 2 and len(self.stderr_lines) == 1
                and "Traceback" not in self.stderr_lines[0] and says in self.stderr_lines[0])


def run(case: BadInput, timeout_s: float = 120.0) -> Outcome:
    """Run the real CLI as a process; its exit code and non-empty stderr lines."""
    res = subprocess.run([sys.executable, "-m", "mrslam", *case.args], cwd=ROOT,
                         capture_output=True, text=True, timeout=timeout_s,
                         env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"})
    return Outcome(res.returncode, [ln for ln in res.stderr.splitlines() if ln.strip()])
