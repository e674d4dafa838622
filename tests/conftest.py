import os
import sys
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
