#!/usr/bin/env bash
# Prepare .venv for `make demo` / `make test` on a fresh Debian/Ubuntu machine.
# Idempotent: reinstalls only when pyproject.toml or the requested extras change.
#   usage: deploy/bootstrap.sh [EXTRAS]     (default: all,dev; add bench for bench/icp_compare.py)
# The versions come from deploy/constraints.txt (those the tests ran with).
set -euo pipefail
extras="${1:-all,dev}"
cd "$(dirname "$0")/.."

as_root() { [ "$(id -u)" = 0 ]; }
apt_install() {  # apt_install PKG... (root only)
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null 2>&1 || {
    DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
  }
}

# 1. a Python >= 3.11
py=""
for cand in ${PYTHON:-} python3.13 python3.12 python3.11 python3; do
  if command -v "$cand" >/dev/null 2>&1 &&
     "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    py="$cand"; break
  fi
done
if [ -z "$py" ]; then
  echo "mrslam needs Python >= 3.11 (none found on PATH; set PYTHON=/path/to/python3.11)" >&2
  exit 1
fi

# 2. the virtual environment (Debian ships venv separately)
if [ ! -x .venv/bin/python ]; then
  if ! "$py" -m venv .venv >/dev/null 2>&1; then
    rm -rf .venv
    ver=$("$py" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    if as_root; then
      echo "installing python${ver}-venv (Debian's venv module)" >&2
      apt_install "python${ver}-venv" || apt_install python3-venv
      "$py" -m venv .venv
    else
      echo "Python's venv module is missing. Run: sudo apt-get install -y python${ver}-venv" >&2
      exit 1
    fi
  fi
fi

# 3. open3d's system library (only the bench extra installs open3d)
if [[ "$extras" == *bench* ]]; then
  if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if as_root; then
      echo "installing libusb-1.0-0 (needed by open3d)" >&2
      apt_install libusb-1.0-0
    else
      echo "open3d needs libusb. Run: sudo apt-get install -y libusb-1.0-0" >&2
      exit 1
    fi
  fi
fi

# 4. the motor-base firmware's toolchain and AVR simulator, for its tests (dev only; see
#    deploy/firmware/README.md). Without root the firmware tests skip and say what to install.
if [[ "$extras" == *dev* ]]; then
  avr_pkgs="gcc-avr avr-libc binutils-avr libsimavr-dev libelf-dev"
  if ! command -v avr-g++ >/dev/null 2>&1 || [ ! -f /usr/include/simavr/sim_avr.h ] ||
     [ ! -f /usr/include/gelf.h ]; then
    if as_root; then
      echo "installing the AVR toolchain and simavr (the motor-base firmware's tests)" >&2
      # shellcheck disable=SC2086
      apt_install $avr_pkgs
    else
      echo "no AVR toolchain: the firmware tests will skip. Run: sudo apt-get install -y $avr_pkgs" >&2
    fi
  fi
fi

# 5. a browser for the operator console's tests (dev only; docs/console.md): Debian's chromium,
#    which playwright drives (its own browser download is not used). Without root the browser
#    tests skip and say what to install.
if [[ "$extras" == *dev* ]]; then
  if ! command -v chromium >/dev/null 2>&1; then
    if as_root; then
      echo "installing chromium (the operator console's browser tests)" >&2
      apt_install chromium
    else
      echo "no chromium: the console's browser tests will skip. Run: sudo apt-get install -y chromium" >&2
    fi
  fi
fi

# 6. the project and its extras
stamp=".venv/.installed-$(cat pyproject.toml deploy/constraints.txt <(echo "$extras") |
  sha1sum | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  echo "installing mrslam[$extras] into .venv (first run takes a minute)" >&2
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q --disable-pip-version-check \
    -c deploy/constraints.txt -e ".[$extras]"
  rm -f .venv/.installed-*
  touch "$stamp"
fi
