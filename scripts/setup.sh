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

# Libraries the gmsh wheel's libgmsh links against (OpenGL utility, X client libraries),
# though the project only uses its mesher.
for lib in libGLU.so.1 libXcursor.so.1 libXft.so.2 libXinerama.so.1 libGL.so.1; do
  if ! ldconfig -p | grep -q "$lib"; then
    SUDO=""
    [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libglu1-mesa libxcursor1 libxft2 libxinerama1 libgl1 >/dev/null
    break
  fi
done

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
# The packages: skipped when this script and pyproject.toml are those of the last
# successful install (pip's own check of every requirement took ~12 s of each re-run; the
# package itself is installed editable, so source changes need no reinstall).
STAMP=.venv/.tissuetwin-install.sha256
WANT="$(cat scripts/setup.sh pyproject.toml | sha256sum | cut -d' ' -f1)"
if [ ! -x .venv/bin/tissuetwin ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  rm -f "$STAMP"
  # torch first, pinned: the local CPU wheel. An unpinned torch would pull gigabytes of CUDA.
  .venv/bin/python -m pip install -q --disable-pip-version-check torch==2.13.0
  .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[dev]'
  echo "$WANT" > "$STAMP"
fi
# numba compiles the simulation's kernels on first use (about 100 s on 2 cores) and caches
# them beside the sources; compile them here, once per install, not in a user's first replay.
.venv/bin/tissuetwin precompile
