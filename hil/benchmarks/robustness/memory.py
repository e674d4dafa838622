"""Part ``memory``: the peak RSS of a long in-process run over a short one's: flat, not growing
with the run's length.
"""
from __future__ import annotations

import random
import subprocess
import tempfile
import time
from pathlib import Path

from ...testing import ROOT, SCENARIOS, hil_cmd, last_line, subprocess_env
from .probe import Part

#: the long run's peak RSS over the short one's that still counts as flat
MEMORY_RATIO_MAX = 1.2


def _vm_hwm_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except (OSError, ValueError):  # the process is gone or /proc unreadable: not measured
        return None
    return None


def peak_rss_run(seconds: float, tmp: Path, seed: int) -> dict:
    """Peak RSS of one in-process ``hil run``: its own high-water mark (``VmHWM``), read every 50 ms until
    it exits (the last 50 ms can be missed).  Not ``wait4``'s ``ru_maxrss``: Linux carries the forking
    process's high-water mark into the child across ``exec``, so it reports this bench's own peak."""
    err_path = tmp / f"m{seconds:g}.err"
    with open(err_path, "w") as err:
        proc = subprocess.Popen(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", "inprocess", "--seed", seed,
                                        "--out", tmp / f"m{seconds:g}", "--no-rrd", "--json",
                                        "--set", f"run.duration_s={seconds}", "--set", f"run.fault_time_s={seconds - 0.5}"),
                                cwd=ROOT, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=err,
                                stdin=subprocess.DEVNULL)
    t0 = time.monotonic()
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _vm_hwm_kb(proc.pid) or 0)
        time.sleep(0.05)
    return {"seconds": seconds, "exit": proc.returncode, "peak_rss_mb": round(peak / 1024, 1),
            "wall_s": round(time.monotonic() - t0, 1), "last_line": last_line(err_path.read_text())[:200]}


def part_memory(seed: int, seconds: tuple[float, float], log) -> dict:
    a, b = seconds
    part = Part("memory", seed, f"peak RSS of a {b:g} s run over a {a:g} s run (in-process lockstep): at most "
                f"{MEMORY_RATIO_MAX:g}")
    rng = random.Random(f"{seed}:memory")
    run_seed = rng.randrange(1, 10 ** 6)
    with tempfile.TemporaryDirectory(prefix="hil-robust-mem-") as tmp:
        runs = []
        for s in (a, b):
            log(f"bench robustness: memory: a {s:g} s run (seed {run_seed})")
            runs.append(peak_rss_run(s, Path(tmp), run_seed))
            part.cases += 1
    for r in runs:
        if r["exit"] != 0:
            part.fail(f"{r['seconds']:g} s", "run failed", f"exit {r['exit']}: {r['last_line']}")
    ratio = runs[1]["peak_rss_mb"] / runs[0]["peak_rss_mb"] if runs[0]["peak_rss_mb"] else None
    part.figures = {"run_seed": run_seed, "runs": runs, "ratio": None if ratio is None else round(ratio, 3)}
    if ratio is None or ratio > MEMORY_RATIO_MAX:
        part.fail("ratio", "memory grows with the run's length", f"peak RSS {runs[0]['peak_rss_mb']} MB ({a:g} s) -> "
                  f"{runs[1]['peak_rss_mb']} MB ({b:g} s): ratio {ratio}")
    return part.done()
