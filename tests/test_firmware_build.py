"""The motor-base firmware builds for the Mega 2560 with avr-gcc, warnings as errors."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.support_firmware import FIRMWARE, make, require_toolchain

#: runs make and the AVR compiler: the e2e tier
pytestmark = pytest.mark.e2e

FLASH, SRAM = 256 * 1024, 8 * 1024      # ATmega2560


@pytest.fixture(autouse=True)
def toolchain() -> None:
    require_toolchain()


def test_the_firmware_builds_for_the_mega_2560_without_a_warning(tmp_path: Path) -> None:
    out = make("firmware", BUILD=str(tmp_path))
    log = out.stdout + out.stderr
    assert out.returncode == 0, log
    assert "warning" not in log.lower()
    assert "-Wall -Wextra -Werror" in log and "-mmcu=atmega2560" in log
    elf = tmp_path / "base.elf"
    head = elf.read_bytes()[:20]
    assert head[:4] == b"\x7fELF" and int.from_bytes(head[18:20], "little") == 83   # EM_AVR
    sizes = subprocess.run(["avr-size", "-A", str(elf)], capture_output=True, text=True,
                           check=True).stdout
    section = {f[0]: int(f[1]) for f in (line.split() for line in sizes.splitlines())
               if len(f) >= 2 and f[0].startswith(".") and f[1].isdigit()}
    assert section[".text"] + section.get(".data", 0) < FLASH // 8
    # static RAM leaves most of the 8 KiB to the stack
    assert section.get(".data", 0) + section.get(".bss", 0) < SRAM // 8
    hex_lines = (tmp_path / "base.hex").read_text().splitlines()
    assert hex_lines[-1] == ":00000001FF" and all(h.startswith(":") for h in hex_lines)


def test_a_warning_fails_the_build(tmp_path: Path) -> None:
    src = (FIRMWARE / "base" / "base.ino").read_text()
    bad = tmp_path / "bad.ino"
    bad.write_text(src.replace("void setup() {", "void setup() {\n  int unused_here = 1;", 1))
    out = make("firmware", SRC=str(bad), BUILD=str(tmp_path / "build"))
    assert out.returncode != 0
    assert "unused_here" in out.stderr and "-Werror=unused-variable" in out.stderr
    assert not (tmp_path / "build" / "base.hex").exists()
