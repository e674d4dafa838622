"""Part ``scenarios``: mutated scenario files (``hil.testing.mutate``) loaded in process under a
watchdog, and some of them through the real ``hil run`` in a sandbox.
"""
from __future__ import annotations

import collections
import os
import random
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from ...errors import HilError
from ...testing import SET_CHOICES, files_under, first_traceback, full_scenario_text, hil_cmd, last_line, mutate, \
    stop, subprocess_env
from .probe import RUN_TIMEOUT_S, Part

#: a probe that takes longer than this is a hang (in-process scenario loading)
LOAD_TIMEOUT_S = 10.0


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def load_mutant(path: Path, sets) -> tuple[str, str]:
    """(outcome, detail): "loaded" (detail: steps), "refused" (the one line), "traceback", "hang"."""
    from ...config import load_scenario, parse_set

    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, LOAD_TIMEOUT_S)
    try:
        s = load_scenario(path, parse_set(sets))
        return "loaded", str(s.steps)
    except _Timeout:  # the finding: loading hung
        return "hang", f"load_scenario took more than {LOAD_TIMEOUT_S:g} s"
    except HilError as e:
        msg = str(e)
        if not msg or "\n" in msg or "\r" in msg or len(msg) >= 600 or not (msg.startswith(str(path))
                                                                           or msg.startswith("--set")):
            return "bad_message", repr(msg[:300])
        return "refused", msg
    except RecursionError as e:
        return "traceback", f"RecursionError: {e}"
    except Exception as e:  # noqa: BLE001 - the point of the probe
        return "traceback", f"{type(e).__name__}: {e}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)





def run_mutant(data: bytes, sets, sandbox_parent: Path, timeout_s: float) -> dict:
    """The mutant through ``hil run --bus inprocess`` in a sandbox: exit, traceback?, hang?, files written
    outside --out."""
    box = Path(tempfile.mkdtemp(prefix="box-", dir=sandbox_parent))
    for d in ("scen", "out", "home", "tmp", "run"):
        (box / d).mkdir(mode=0o700)
    (box / "scen" / "m.toml").write_bytes(data)
    before = files_under(box)
    cmd = hil_cmd("run", "scen/m.toml", "--bus", "inprocess", "--out", "out", "--no-rrd", "--json")
    for item in sets:
        cmd += ["--set", item]
    env = subprocess_env(HOME=box / "home", TMPDIR=box / "tmp", XDG_RUNTIME_DIR=box / "run", MPLCONFIGDIR=box / "tmp")
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=box, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)
    hung = False
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:  # the finding: the command hung; stopped, then judged
        hung = True
        stop(proc)
        out, err = proc.communicate()
    outside = sorted(p for p in files_under(box) - before if not (p == "out" or p.startswith("out" + os.sep)))
    shutil.rmtree(box, ignore_errors=True)
    return {"exit": proc.returncode, "hung": hung, "traceback": "Traceback" in err, "traceback_text": first_traceback(err),
            "outside": outside,
            "stderr_last": last_line(err), "stderr_lines": len(err.strip().splitlines()),
            "wall_s": time.monotonic() - t0}


def part_scenarios(seed: int, count: int, runs: int, log, max_run_steps: int = 30_000) -> dict:
    from ...progress import Progress

    part = Part("scenarios", seed, f"{count} mutated scenario files loaded in process and {runs} of them through "
                "`hil run`: 0 tracebacks, 0 hangs, 0 writes outside --out")
    rng = random.Random(f"{seed}:scenarios")
    base = full_scenario_text()
    outcomes = collections.Counter()
    slowest = (0.0, -1)
    mutants = []
    with tempfile.TemporaryDirectory(prefix="hil-robust-scen-") as tmp:
        tmp = Path(tmp)
        path = tmp / "m.toml"
        path.write_text(base)
        for sets in SET_CHOICES:     # warm: the first load imports and compiles what a scenario needs (not timed)
            from ...config import load_scenario, parse_set
            load_scenario(path, parse_set(list(sets)))
        bar = Progress(count, "bench robustness: scenarios: loading")
        for i in range(count):
            what, data = mutate(base, rng)
            sets = list(rng.choice(SET_CHOICES))
            path.write_bytes(data)
            t0 = time.perf_counter()
            outcome, detail = load_mutant(path, sets)
            took = time.perf_counter() - t0
            slowest = max(slowest, (took, i))
            outcomes[outcome] += 1
            part.cases += 1
            mutants.append((i, what, data, sets, outcome, detail))
            if outcome in ("traceback", "hang", "bad_message"):
                part.fail(i, what, f"{outcome}: {detail}")
            bar.update(i + 1)
        bar.close()
        # the full runs: loaded mutants of a sensible length and refused ones, half each where possible
        loaded = [m for m in mutants if m[4] == "loaded" and int(m[5]) <= max_run_steps]
        refused = [m for m in mutants if m[4] == "refused"]
        long_ = sum(1 for m in mutants if m[4] == "loaded" and int(m[5]) > max_run_steps)
        pick = rng.sample(loaded, min(len(loaded), (runs + 1) // 2))
        pick += rng.sample(refused, min(len(refused), runs - len(pick)))
        run_out = collections.Counter()
        outside_total = run_tracebacks = 0
        run_refused = []           # loaded in process, refused by hil run in one line (exit 2): allowed, listed
        bar = Progress(max(len(pick), 1), "bench robustness: scenarios: hil run")
        for j, (i, what, data, sets, outcome, detail) in enumerate(sorted(pick)):
            r = run_mutant(data, sets, tmp, RUN_TIMEOUT_S)
            run_out[f"exit {r['exit']}" if not r["hung"] else "hang"] += 1
            outside_total += len(r["outside"])
            if r["hung"]:
                part.fail(i, what, f"hil run did not end within {RUN_TIMEOUT_S:g} s")
            elif r["traceback"]:
                run_tracebacks += 1
                part.fail(i, what, f"hil run printed a traceback: {r['stderr_last']}; {r['traceback_text']}")
            elif r["exit"] not in (0, 2):
                part.fail(i, what, f"hil run exit {r['exit']}: {r['stderr_last']}")
            elif r["exit"] == 2 and not r["stderr_last"].startswith("hil run: error: "):
                part.fail(i, what, f"exit 2 without the one error line: {r['stderr_last']}")
            elif r["exit"] == 0 and outcome != "loaded":
                part.fail(i, what, f"refused in process ({detail}) but hil run ran it")
            elif r["exit"] == 2 and outcome == "loaded":
                run_refused.append({"case": i, "what": what, "line": r["stderr_last"][:200]})
            if r["outside"]:
                part.fail(i, what, f"hil run wrote outside --out: {r['outside'][:5]}")
            bar.update(j + 1)
        bar.close()
    part.figures = {"mutants": count, "loaded": outcomes["loaded"], "refused": outcomes["refused"],
                    "tracebacks": outcomes["traceback"], "hangs": outcomes["hang"],
                    "bad_messages": outcomes["bad_message"], "slowest_load_s": round(slowest[0], 3),
                    "slowest_case": slowest[1], "runs": len(pick), "run_outcomes": dict(run_out),
                    "run_tracebacks": run_tracebacks, "loaded_but_refused_by_run": run_refused,
                    "run_hangs": run_out["hang"], "writes_outside_out": outside_total,
                    "loaded_but_too_long_to_run": long_}
    return part.done()
