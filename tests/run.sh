#!/usr/bin/env bash
# The whole test suite, from a fresh clone: makes the virtualenv, installs the package and what the
# bus and viewer tests need, runs pytest on the host with the vcan tests on real SocketCAN vcan0 beside it
# (natively when this kernel has vcan, otherwise inside User-Mode Linux).
#   bash tests/run.sh            everything (what CI runs)
#   bash tests/run.sh --fast     the fast tier: all but the tests marked slow, vcan or realtime, including
#                                one real two-process run over the local bus; minutes on a warm tree
# Other arguments go to pytest.  Seeds of generated cases: fixed unless HIL_TEST_SEED says otherwise
# (an integer pins the base seed, "random" draws one); under CI=true they are drawn (tests/conftest.py).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
say() { echo "== [${SECONDS} s] $*" >&2; }     # progress, with the seconds since the start
PY=${PYTHON:-python3}

FAST=0
ARGS=()
for a in "$@"; do
  if [ "$a" = "--fast" ]; then FAST=1; else ARGS+=("$a"); fi
done
set -- ${ARGS[@]+"${ARGS[@]}"}

if [ "${CI:-}" = "true" ] && [ -z "${HIL_TEST_SEED:-}" ]; then HIL_TEST_SEED=random; fi
if [ "${HIL_TEST_SEED:-}" = "random" ]; then   # one base seed for the host, vcan and real-time sessions
  HIL_TEST_SEED=$(( $(od -An -N4 -tu4 /dev/urandom | tr -d ' ') % 2147483648 ))
  say "test seeds drawn at random: HIL_TEST_SEED=$HIL_TEST_SEED reproduces them"
fi
[ -n "${HIL_TEST_SEED:-}" ] && export HIL_TEST_SEED

# Debian packages: UML + can-utils for the vcan tests, Vulkan for Rerun's headless viewer (neither in the
# fast tier), gcc for our FMU.  apt-get runs in the background while pip installs; both are waited for
# before any test starts.
NEED_DEB=()
command -v gcc >/dev/null 2>&1 || NEED_DEB+=(gcc)          # building our FMU
if [ "$FAST" = 0 ]; then
  command -v linux >/dev/null 2>&1 || [ -x /usr/bin/linux ] || NEED_DEB+=(user-mode-linux)
  command -v insmod >/dev/null 2>&1 || [ -x /usr/sbin/insmod ] || [ -x /sbin/insmod ] || NEED_DEB+=(kmod)
  command -v candump >/dev/null 2>&1 || NEED_DEB+=(can-utils)
  dpkg -s mesa-vulkan-drivers >/dev/null 2>&1 || NEED_DEB+=(mesa-vulkan-drivers)
  dpkg -s libvulkan1 >/dev/null 2>&1 || NEED_DEB+=(libvulkan1)
fi
apt_pid=""
APT_LOG=""
if [ ${#NEED_DEB[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    say "apt-get install ${NEED_DEB[*]} (in the background)"
    APT_LOG=$(mktemp /tmp/hil-apt-log.XXXXXX)
    ( export DEBIAN_FRONTEND=noninteractive
      apt-get update -qq && apt-get install -y -qq --no-install-recommends "${NEED_DEB[@]}" ) \
      > "$APT_LOG" 2>&1 < /dev/null &
    apt_pid=$!
  else
    say "not root: cannot install ${NEED_DEB[*]}; the tests that need them will say so"
  fi
fi

if [ ! -x .venv/bin/python ]; then
  say "creating .venv"
  "$PY" -m venv .venv
fi
# The installs are skipped when the stamp says they were done for this pyproject.toml and this list, and
# the package still imports from this tree (a warm tree: seconds, not a minute of pip).
GEMSEO_FMU="gemseo-fmu==3.1.1"
STAMP=.venv/.hil-tests-installed
WANT="$(sha256sum pyproject.toml | cut -d' ' -f1) .[test,docs] $GEMSEO_FMU $ROOT"
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ] \
   && (cd / && "$ROOT/.venv/bin/python" -I -c "import hil, sys; sys.exit(not hil.__file__.startswith('$ROOT/'))") 2>/dev/null; then
  say "package and test dependencies installed for this pyproject.toml ($STAMP): no pip"
else
  say "installing the package and test dependencies"
  rm -f "$STAMP"
  # uv when PyPI gives it (faster than pip, the same packages: docs/design/ci.md), compiling the bytecode
  # as pip does (CI sets PYTHONDONTWRITEBYTECODE: without it every process compiles its imports again);
  # pip otherwise.  Third-party FMUs for tests/test_fmu.py: gemseo-fmu with --no-deps (it pins
  # fmpy<=0.3.19 and pulls gemseo[all]).
  if .venv/bin/python -m pip install -q --disable-pip-version-check uv >/dev/null 2>&1 && [ -x .venv/bin/uv ]; then
    .venv/bin/uv pip install -q --compile-bytecode --python .venv/bin/python -e ".[test,docs]"
    .venv/bin/uv pip install -q --compile-bytecode --python .venv/bin/python --no-deps "$GEMSEO_FMU"
  else
    say "uv not installed from the registry: pip"
    .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
    .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test,docs]"
    .venv/bin/python -m pip install -q --disable-pip-version-check --no-deps "$GEMSEO_FMU"
  fi
  echo "$WANT" > "$STAMP"
fi

# The identifier's kernels compiled before any test runs hil: a first run says so on stderr, which the tests
# that read a run's stderr do not expect (numba caches them beside the source; later runs load them).
.venv/bin/python -c "from hil.progress import compile_kernels; compile_kernels('tests/run.sh')"

if [ -n "$apt_pid" ]; then
  apt_rc=0
  wait "$apt_pid" || apt_rc=$?
  apt_pid=""
  if [ "$apt_rc" = 0 ]; then say "apt-get install: done"
  else say "apt-get install ${NEED_DEB[*]}: exit $apt_rc"; tail -n 20 "$APT_LOG" >&2; fi
  rm -f "$APT_LOG"
fi

mkdir -p tests/artefacts
PYTEST=(.venv/bin/python -m pytest)
# Two workers (pytest-xdist) stealing tests from each other (--dist worksteal: the gap tests, half of the
# host's time, would hold one worker for all of it a file at a time; a module's recorded run is then made
# at most once per worker); the tests marked serial or realtime time the machine and run alone.
PARALLEL=(-n 2 --dist worksteal)
if [ "$FAST" = 1 ]; then
  say "pytest --fast (all but the slow, vcan and real-time tests; two workers)"
  status=0
  "${PYTEST[@]}" "${PARALLEL[@]}" -m "not slow and not vcan and not realtime and not serial" --durations=10 "$@" \
    || status=$?
  say "pytest --fast: the tests that time the machine, alone"
  rt_rc=0
  "${PYTEST[@]}" -m "serial and not slow and not vcan and not realtime" "$@" || rt_rc=$?
  [ "$rt_rc" = 0 ] || [ "$rt_rc" = 5 ] || status=$rt_rc      # 5: arguments that select none of them
  exit $status
fi

status=0
# The vcan tests (inside User-Mode Linux: minutes, mostly the guest's Python start-ups) run beside the
# host tests; the tests that time the machine (serial, realtime) run alone once both are done.
VCAN_RUNNER=$(ls tests/uml/run_vcan_tests.sh tests/uml/run_in_uml.sh 2>/dev/null | head -n 1 || true)
VCAN_LOG=$(mktemp /tmp/hil-vcan-log.XXXXXX)
vcan_pid=""
cleanup() {   # interrupted or done: the background vcan run (and the UML under it) stops with us, its log goes
  if [ -n "$vcan_pid" ]; then
    command -v pkill >/dev/null && pkill -TERM -P "$vcan_pid" 2>/dev/null
    kill "$vcan_pid" 2>/dev/null || true
  fi
  rm -f "$VCAN_LOG"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
if [ -n "$VCAN_RUNNER" ]; then
  say "pytest -m vcan (SocketCAN vcan0, $VCAN_RUNNER) started beside the host tests; its output follows them"
  bash "$VCAN_RUNNER" > "$VCAN_LOG" 2>&1 < /dev/null &
  vcan_pid=$!
elif [ "${CI:-}" = "true" ]; then
  say "vcan tests: no runner in tests/uml/, and under CI=true they must run"
  status=1
fi

say "pytest (host, all but the vcan tests and those that time the machine; two workers)"
"${PYTEST[@]}" "${PARALLEL[@]}" -m "not vcan and not realtime and not serial" --durations=40 "$@" || status=$?

if [ -n "$vcan_pid" ]; then
  waited=0
  while kill -0 "$vcan_pid" 2>/dev/null; do
    sleep 5; waited=$((waited + 5))
    [ $((waited % 30)) = 0 ] && say "waiting for the vcan tests ($waited s)"
  done
  vcan_rc=0
  wait "$vcan_pid" || vcan_rc=$?
  say "pytest -m vcan (SocketCAN vcan0, $VCAN_RUNNER): exit $vcan_rc"
  cat "$VCAN_LOG"
  [ "$vcan_rc" = 0 ] || status=$vcan_rc
  vcan_pid=""
fi

say "pytest (host, the tests that time the machine: real-time runs, pacing, CPU shares; alone)"
rt_rc=0
"${PYTEST[@]}" -m "(realtime or serial) and not vcan" --durations=5 "$@" || rt_rc=$?
[ "$rt_rc" = 0 ] || [ "$rt_rc" = 5 ] || status=$rt_rc      # 5: arguments that select none of them
say "tests/run.sh: exit $status"
exit $status
