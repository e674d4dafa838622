#!/usr/bin/env bash
# The whole test suite, from a fresh clone: makes the virtualenv, installs the package and what the
# bus and viewer tests need, runs pytest on the host, then the vcan tests on real SocketCAN vcan0
# (natively when this kernel has vcan, otherwise inside User-Mode Linux).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
PY=${PYTHON:-python3}

if [ ! -x .venv/bin/python ]; then
  echo "== creating .venv" >&2
  "$PY" -m venv .venv
fi
echo "== installing the package and test dependencies" >&2
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
# third-party FMUs for tests/test_fmu.py; --no-deps: gemseo-fmu pins fmpy<=0.3.19 and pulls gemseo[all]
.venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "gemseo-fmu==3.1.1"

# Debian packages: UML + can-utils for the vcan tests, Vulkan for Rerun's headless viewer.
NEED_DEB=()
command -v linux >/dev/null 2>&1 || [ -x /usr/bin/linux ] || NEED_DEB+=(user-mode-linux)
command -v insmod >/dev/null 2>&1 || [ -x /usr/sbin/insmod ] || [ -x /sbin/insmod ] || NEED_DEB+=(kmod)
command -v candump >/dev/null 2>&1 || NEED_DEB+=(can-utils)
command -v gcc >/dev/null 2>&1 || NEED_DEB+=(gcc)          # building our FMU
dpkg -s mesa-vulkan-drivers >/dev/null 2>&1 || NEED_DEB+=(mesa-vulkan-drivers)
dpkg -s libvulkan1 >/dev/null 2>&1 || NEED_DEB+=(libvulkan1)
if [ ${#NEED_DEB[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "== apt-get install ${NEED_DEB[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq --no-install-recommends "${NEED_DEB[@]}" >/dev/null
  else
    echo "== not root: cannot install ${NEED_DEB[*]}; the tests that need them will say so" >&2
  fi
fi

mkdir -p tests/artefacts
status=0
echo "== pytest (host)" >&2
.venv/bin/python -m pytest -m "not vcan" "$@" || status=$?

VCAN_RUNNER=$(ls tests/uml/run_vcan_tests.sh tests/uml/run_in_uml.sh 2>/dev/null | head -n 1 || true)
if [ -n "$VCAN_RUNNER" ]; then
  echo "== pytest -m vcan (SocketCAN vcan0, $VCAN_RUNNER)" >&2
  bash "$VCAN_RUNNER" || status=$?
elif [ "${CI:-}" = "true" ]; then
  echo "== vcan tests: no runner in tests/uml/, and under CI=true they must run" >&2
  status=1
fi
exit $status
