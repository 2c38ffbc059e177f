#!/usr/bin/env bash
# Install Tissue Twin and everything it needs into ./.venv on a fresh Debian machine
# with Python 3.11. Idempotent: re-running only checks what is there.
set -euo pipefail
cd "$(dirname "$0")/.."

# System libraries open3d links against (libusb, OpenMP runtime).
if ! ldconfig -p | grep -q 'libusb-1.0.so.0' || ! ldconfig -p | grep -q 'libgomp.so.1'; then
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi

# Debian chromium for the workbench's headless browser tests (playwright drives it;
# `playwright install` cannot download browsers here).
if ! command -v chromium >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi

# Debian's PostgreSQL server for tests/app/test_postgres.py (it starts a throwaway server
# on loopback; DATABASE_URL points the workbench at PostgreSQL, see docker-compose.yml).
if ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq postgresql >/dev/null
fi

PYTHON="${PYTHON:-python3.11}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
# torch first, pinned: the local CPU wheel. An unpinned torch would pull gigabytes of CUDA.
.venv/bin/python -m pip install -q --disable-pip-version-check torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
