import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"


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
