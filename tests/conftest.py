import signal
import subprocess
import time
from pathlib import Path

import pytest
from hil.testing import hil_command, subprocess_env
from hil.testing import run_hil as hil  # noqa: F401 (tests import it from here)

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"


@pytest.fixture
def ffcc_a_path():
    return SCENARIOS / "ffcc_a.toml"


@pytest.fixture
def ffcc_b_path():
    return SCENARIOS / "ffcc_b.toml"


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
