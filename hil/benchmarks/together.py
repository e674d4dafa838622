"""Probe processes started together: the idle loop's pacers and the vCPU probe's spinners.

Each process prints ``ready`` once imported and scheduled; then all of them get one start time ``t0``
on stdin (``time.perf_counter``: CLOCK_MONOTONIC on Linux, one clock for every process), so their
periods and gaps line up; each prints one JSON line when done. Why ``t0`` only after every ``ready``:
an import takes longer than the lead, and a process that starts late would miss its first periods.
"""
from __future__ import annotations

import json
import subprocess
import time

from ..errors import HilError


def run_together(cmds: list[list[str]], what: str, lead_s: float = 0.05) -> list[dict]:
    """Start ``cmds``, wait for every ``ready``, send ``t0 = now + lead_s``, return their JSON results in
    order; ``what`` names them in the errors (a process that does not start, fails or prints no result)."""
    children = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stdin=subprocess.PIPE, text=True) for cmd in cmds]
    try:
        for child in children:
            if child.stdout.readline().strip() != "ready":
                raise HilError(f"{what} did not start (exit {child.wait()})")
        t0 = time.perf_counter() + lead_s
        for child in children:
            child.stdin.write(f"{t0!r}\n")
            child.stdin.close()
        outs = []
        for child in children:
            out = child.stdout.read()
            if child.wait() != 0:
                raise HilError(f"{what} exited {child.returncode}")
            try:
                outs.append(json.loads(out))
            except ValueError:
                raise HilError(f"{what} printed no result ({out[:80]!r})") from None
        return outs
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
                child.wait()
