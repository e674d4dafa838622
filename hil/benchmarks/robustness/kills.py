"""Part ``kills``: SIGKILL of a run's TCU, plant or hub at a random point; the run ends in one line
and its log is readable up to the kill.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import tempfile
import time
from pathlib import Path

from ...testing import ROOT, SCENARIOS, alive, children_of, cmdline, first_traceback, hil_cmd, last_line, stop, \
    subprocess_env
from .probe import Part


#: what kill_run kills: the TCU and the plant of a local-bus run, the hub process of a hub run
KILL_VICTIMS = ("tcu", "plant", "hub")


def kill_run(tmp: Path, victim: str, seed: int, min_bytes: int) -> dict:
    """A run SIGKILLed once its log has ``min_bytes``: its TCU or the plant (over the local bus), or
    the hub process the plant started (over the hub)."""
    from ...log.read import read_log

    out = tmp / f"{victim}-{seed}"
    path = out / f"ffcc_a-gp-{seed}.mcap"
    bus = "hub" if victim == "hub" else "local"
    proc = subprocess.Popen(hil_cmd("run", SCENARIOS / "ffcc_a.toml", "--bus", bus, "--seed", seed, "--out", out,
                                    "--no-rrd", "--set", "run.duration_s=60", "--set", "run.fault_time_s=55"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
    res = {"victim": victim, "bus": bus, "seed": seed, "kill_at_bytes": min_bytes}
    try:
        end = time.monotonic() + 120
        tcu = hub = None
        while time.monotonic() < end and proc.poll() is None:
            kids = children_of(proc.pid)
            if tcu is None:
                tcu = next((p for p in kids if "hil.tcu_node" in cmdline(p)), None)
            if hub is None and bus == "hub":
                hub = next((p for p in kids if "can_remote" in cmdline(p)), None)
            if path.exists() and path.stat().st_size >= min_bytes and tcu is not None and (hub or bus != "hub"):
                break
            time.sleep(0.02)
        if proc.poll() is not None:
            res["error"] = f"the run ended before the kill (exit {proc.returncode})"
            return res
        os.kill({"tcu": tcu, "hub": hub}.get(victim, proc.pid), signal.SIGKILL)
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:  # a hang after the kill is the finding, recorded
            res["error"] = "the run did not end within 60 s of the kill"
            return res
        res["exit"] = proc.returncode
        res["traceback"] = "Traceback" in err
        res["traceback_text"] = first_traceback(err)
        res["last_line"] = last_line(err)
        t0 = time.monotonic()
        while alive(tcu) and time.monotonic() - t0 < 10:
            time.sleep(0.05)
        res["tcu_left_running"] = alive(tcu)
        got = read_log(path)
        res.update(log_bytes=path.stat().st_size, messages=got.message_count, cut=got.cut, damage=bool(got.damage),
                   ended_early=got.ended_early[:120], states=len(got.topic("/plant/state")))
    finally:
        stop(proc)
    return res


def part_kills(seed: int, count: int, log) -> dict:
    part = Part("kills", seed, f"SIGKILL of the TCU, of the plant and of the hub, {count} each: the TCU's and the "
                "hub's give exit 3 in one line and a log closed with the fault; the plant's leaves no TCU and a log "
                "readable up to the kill")
    rng = random.Random(f"{seed}:kills")
    runs = []
    with tempfile.TemporaryDirectory(prefix="hil-robust-kills-") as tmp:
        for i in range(len(KILL_VICTIMS) * count):
            victim = KILL_VICTIMS[i % len(KILL_VICTIMS)]
            run_seed, at = rng.randrange(1, 10 ** 6), rng.randrange(100_000, 600_000)
            log(f"bench robustness: kills: case {i}: SIGKILL the {victim} at {at} log bytes (seed {run_seed})")
            r = kill_run(Path(tmp), victim, run_seed, at)
            runs.append(r)
            part.cases += 1
            what = f"SIGKILL {victim} at {at} bytes, run seed {run_seed}"
            if "error" in r:
                part.fail(i, what, r["error"])
                continue
            if r["traceback"]:
                part.fail(i, what, f"traceback: {r['last_line']}; {r['traceback_text']}")
            if r["tcu_left_running"]:
                part.fail(i, what, "the TCU process outlived its run")
            if not r["messages"] or not r["states"]:
                part.fail(i, what, "nothing readable in the log")
            if victim in ("tcu", "hub"):
                says = "TCU process was killed by SIGKILL" if victim == "tcu" else "its hub process or interface is gone"
                if r["exit"] != 3 or says not in r["last_line"] or not r["last_line"].startswith("hil run: error: "):
                    part.fail(i, what, f"exit {r['exit']}: {r['last_line']}")
                if r["damage"] or not r["ended_early"].startswith("fault at step"):
                    part.fail(i, what, f"log not closed with the fault: damage {r['damage']}, {r['ended_early']!r}")
            elif r["exit"] != -signal.SIGKILL:
                part.fail(i, what, f"exit {r['exit']}")
    part.figures = {"runs": runs}
    return part.done()
