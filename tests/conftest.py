import hashlib
import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"

# -- seeds of generated cases --------------------------------------------------------------------------
# HIL_TEST_SEED unset: the fixed base seed below (a run is reproducible); an integer: that base seed;
# "random": a base seed drawn once when the session starts (printed in the header and the summary, and
# handed to xdist's workers through the environment).  tests/run.sh sets "random" under CI=true.
FIXED_BASE_SEED = 20240601
_SEED_COUNTS: dict = {}
_SEED_MODE = {"": "fixed", "random": "drawn at random"}.get(os.environ.get("HIL_TEST_SEED", "").strip(), "pinned")


def _base_seed() -> int:
    value = os.environ.get("HIL_TEST_SEED", "").strip()
    if value == "":
        return FIXED_BASE_SEED
    if value == "random":           # only when this process is not under a session that resolved it
        value = os.environ["HIL_TEST_SEED"] = str(secrets.randbits(31))
    try:
        return int(value)
    except ValueError:
        raise pytest.UsageError(f"HIL_TEST_SEED={value!r}: expected unset, an integer or 'random'") from None


def case_seed(what: str = "") -> int:
    """The seed of a generated case in the running test: a hash of the base seed (HIL_TEST_SEED), the
    test's node id and ``what``, in [0, 2**31).  The n-th call with the same ``what`` in one test gets
    its own seed (n is part of the hash), so a test drawing several cases draws different ones, the
    same on every run with the same base seed.  Printed (shown with the test's output when it fails),
    with what reproduces it: ``HIL_TEST_SEED=<base> pytest <node id>``."""
    current = os.environ.get("PYTEST_CURRENT_TEST", "outside a test (setup)")
    node = current.rsplit(" (", 1)[0]           # "<node id> (setup|call|teardown)"
    head, _, group = node.rpartition("@")       # xdist's loadgroup appends "@<group>": ours is the file
    if head and group == head.split("::", 1)[0]:
        node = head
    base = _base_seed()
    n = _SEED_COUNTS.get((node, what), 0)
    _SEED_COUNTS[node, what] = n + 1
    digest = hashlib.blake2b(f"{base}|{node}|{what}|{n}".encode(), digest_size=8).digest()
    seed = int.from_bytes(digest, "little") % (1 << 31)
    print(f"{what + ': ' if what else ''}seed {seed} (HIL_TEST_SEED={base} pytest {node})")
    return seed


def pytest_configure(config):
    if not hasattr(config, "workerinput"):          # the controller (or a run without xdist) resolves "random"
        _base_seed()


def pytest_report_header(config):
    return f"test seeds: HIL_TEST_SEED={_base_seed()} ({_SEED_MODE})"


def pytest_terminal_summary(terminalreporter):
    terminalreporter.write_line(f"test seeds: HIL_TEST_SEED={_base_seed()} ({_SEED_MODE}) reproduces this run's "
                                "generated cases")


# -- tiers -------------------------------------------------------------------------------------------
# The slow tests: out of the fast tier (``tests/run.sh --fast`` deselects -m slow).  Each took 10 s or
# more in a full run on the 2-core CI machine (pytest --durations); a name matches every parameter case.
# Kept here, in one list, rather than as decorators scattered over the files.
SLOW = {
}
# The tests that time the machine (CPU shares, pacing loops, heartbeats while busy): tests/run.sh runs
# them alone, never beside another xdist worker (the real-time tests have their own marker).
SERIAL = {
    "tests/test_idle_loop.py::test_a_stall_of_the_pacing_loop_shows_as_late_wakes",
    "tests/test_idle_loop.py::test_two_paced_processes_merge_their_late_periods",
    "tests/test_idle_spin.py::test_a_resting_spinner_hands_its_rests_back_and_counts_no_rest_as_a_gap",
    "tests/test_idle_spin.py::test_a_process_preempting_a_spinner_is_never_time_away",
    "tests/test_idle_spin.py::test_spinners_take_nothing_from_a_process_at_normal_priority",
    "tests/test_vcpu_away.py::test_a_process_stopped_by_the_kernel_is_a_guest_gap_not_time_away",
    "tests/test_vcpu_away.py::test_measure_merges_one_spinner_per_cpu",
    "tests/test_tcu_heartbeats.py::test_heartbeats_keep_coming_while_the_tcu_is_held_by_long_work_and_come_from_its_loop_otherwise",
}


@pytest.hookimpl(tryfirst=True)          # before -m deselects (and xdist renames grouped tests)
def pytest_collection_modifyitems(config, items):
    """Marks the SLOW and SERIAL tests, and keeps the tests that share a module-scoped fixture (one
    recorded run read by several tests) on one xdist worker: the fixture is then made once."""
    names = {item.nodeid.split("[", 1)[0] for item in items}
    files = {name.split("::", 1)[0] for name in names}
    whole_files = not any("::" in str(a) for a in config.args)
    for listed in (SLOW, SERIAL):
        gone = {n for n in listed if n.split("::", 1)[0] in files and n not in names}
        if gone and whole_files:
            raise pytest.UsageError(f"tests/conftest.py lists tests that no longer exist: {sorted(gone)}")
    for item in items:
        name = item.nodeid.split("[", 1)[0]
        if name in SLOW:
            item.add_marker(pytest.mark.slow)
        if name in SERIAL:
            item.add_marker(pytest.mark.serial)
        info = getattr(item, "_fixtureinfo", None)
        shared = info and any(d.scope == "module" for defs in info.name2fixturedefs.values() for d in defs)
        if shared:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::", 1)[0]))


@pytest.fixture
def ffcc_a_path():
    return SCENARIOS / "ffcc_a.toml"


@pytest.fixture
def ffcc_b_path():
    return SCENARIOS / "ffcc_b.toml"


def hil_command():
    """The installed console script when present, else the module (same code)."""
    exe = Path(sys.executable).with_name("hil")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "hil.cli"]


def subprocess_env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def hil(*args, timeout: float = 300, cwd=None) -> subprocess.CompletedProcess:
    """``hil ARGS`` as a user runs it, output captured."""
    return subprocess.run(hil_command() + [str(a) for a in args], capture_output=True, text=True,
                          env=subprocess_env(), timeout=timeout, cwd=cwd)


def kill_run_when_log_reaches(args, log_path: Path, min_bytes: int, timeout_s: float = 120.0) -> None:
    """Start ``hil ARGS``, SIGKILL it once ``log_path`` has grown to ``min_bytes`` (a run killed
    halfway, for the crash-recovery tests) and check it died of the signal."""
    proc = subprocess.Popen(hil_command() + list(args), env=subprocess_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and (not log_path.exists() or log_path.stat().st_size < min_bytes):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
