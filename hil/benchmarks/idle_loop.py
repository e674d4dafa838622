"""An idle paced loop: the deadlines a loop that does no work misses on this machine, now.

Why: the real-time issue's target (<= 10 missed deadlines per 10 000 periods of 1 ms) is a property of
the loop *and* of the machine. On a shared virtual machine the vCPU can be away for milliseconds, and
the kernel here is built ``PREEMPT_NONE``. This probe shows what the machine does to a paced loop in
the same minutes as the real runs. It is context, **not a lower bound**: an idle loop leaves its vCPU
idle most of each period, and an idle vCPU can be woken later than a busy one (measured: rounds where
the idle loop missed more deadlines than the real run beside it; ``docs/benchmarks/realtime.md``).

What: two processes (as a real-time run has a plant and a TCU), each at SCHED_FIFO ``priority`` (when
granted; normal priority otherwise, reported), pace periods of ``period_s`` exactly as the plant node
does (sleep until ``WAKE_MARGIN_S`` before the period, then poll with ``POLL_SLICE_S`` sleeps, the last
``SPIN_S`` without sleeping), under the run's CPU latency request when asked (``hil.rt.cpu_latency``)
and beside its idle spinners when it would have them (``hil.rt.idle_spin``),
and do nothing else. Period k of the pair is *missed* when either process
wakes for it later than ``deadline_fraction * period_s`` after its start ``t_k = t0 + k * period_s``
(the bound by which the plant needs the TCU's command). Both processes share ``t0`` on CLOCK_MONOTONIC
(``time.perf_counter`` on Linux), so their late periods are merged by index.

``python -m hil.benchmarks.idle_loop SECONDS [--priority P]`` prints the result as JSON.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time

from ..rt.cpu_latency import CpuLatencyRequest
from ..errors import HilError
from ..rt.idle_spin import SPIN, IdleSpinners, idle_mode
from ..plant_node import POLL_SLICE_S, SPIN_S, WAKE_MARGIN_S
from .together import run_together

#: two processes: the plant's and the TCU's
NODES = 2


def pace(t0: float, period_s: float, steps: int) -> list[float]:
    """Wake for each of ``steps`` periods as the plant node paces itself; the lateness of each wake (s)."""
    late = []
    for k in range(steps):
        t_k = t0 + k * period_s
        now = time.perf_counter()
        if t_k - now > WAKE_MARGIN_S:
            time.sleep(t_k - now - WAKE_MARGIN_S)
        while True:
            now = time.perf_counter()
            if now >= t_k:
                break
            if t_k - now > SPIN_S:
                time.sleep(min(t_k - now - SPIN_S, POLL_SLICE_S))
        late.append(now - t_k)
    return late


def _child(period_s: float, steps: int, priority: int, deadline_s: float) -> None:
    """One pacing process: says "ready" once imported and scheduled, reads t0, paces, prints JSON."""
    granted = False
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            granted = True
        except (AttributeError, PermissionError, OSError):
            # no SCHED_FIFO here: 'granted' stays False and the report says so
            pass
    print("ready", flush=True)
    t0 = float(sys.stdin.readline())
    late = pace(t0, period_s, steps)
    missed = [k for k, x in enumerate(late) if x > deadline_s]
    late_us = sorted(x * 1e6 for x in late)
    print(json.dumps({"missed": missed, "sched_fifo_granted": granted if priority > 0 else None,
                      "late_p99_us": late_us[int(0.99 * (len(late_us) - 1))], "late_max_us": late_us[-1]}))


def kernel_preemption() -> str:
    """The kernel's preemption model, as far as this process can read it: the current mode of a
    ``PREEMPT_DYNAMIC`` kernel from debugfs (``/sys/kernel/debug/sched/preempt``, the one in parentheses),
    else ``preempt=`` on the kernel command line, else the build's default from ``/proc/config.gz``.
    Why it matters: under ``none`` (and ``voluntary``) a SCHED_FIFO task that wakes while the kernel
    runs on its CPU waits until that kernel path reaches a preemption point, milliseconds at times."""
    import gzip
    import re

    try:
        text = open("/sys/kernel/debug/sched/preempt").read()
        m = re.search(r"\((\w+)\)", text)
        if m:
            return f"{m.group(1)} (dynamic)"
    except OSError:  # no debugfs here (or not readable): try the kernel command line
        pass
    try:
        m = re.search(r"(?:^|\s)preempt=(\w+)", open("/proc/cmdline").read())
        if m:
            return f"{m.group(1)} (kernel command line)"
    except OSError:  # no /proc/cmdline: try the kernel config
        pass
    try:
        config = gzip.open("/proc/config.gz", "rt").read()
    except OSError:  # no /proc/config.gz: the report says unknown
        return "unknown"
    for option, name in (("CONFIG_PREEMPT_RT", "rt"), ("CONFIG_PREEMPT_NONE", "none"),
                         ("CONFIG_PREEMPT_VOLUNTARY", "voluntary"), ("CONFIG_PREEMPT_LAZY", "lazy"),
                         ("CONFIG_PREEMPT", "full")):
        if re.search(rf"^{option}=y", config, re.M):
            dynamic = re.search(r"^CONFIG_PREEMPT_DYNAMIC=y", config, re.M)
            return f"{name} (build default{'; dynamic: the current mode is in debugfs, unreadable here' if dynamic else ''})"
    return "unknown"


def measure(seconds: float, priority: int = 0, period_s: float = 1e-3, deadline_fraction: float = 0.9,
            cpu_latency_us: int = -1, idle_spin: str = "off", idle_spin_rest_ms: float = 5.0) -> dict:
    """Run the two empty loops for ``seconds`` and merge them: missed periods (either node late past the
    deadline), per 10 000 periods, the stalls behind them, the load average, SCHED_FIFO granted or not;
    with ``cpu_latency_us`` >= 0 under the CPU latency request a real-time run holds (``hil.rt.cpu_latency``),
    and with the idle spinners it would have by ``idle_spin`` (``hil.rt.idle_spin``): ``cpu_latency_us``
    and ``idle_cpus`` in the result say what was held."""
    latency = CpuLatencyRequest(cpu_latency_us, lambda text: None)
    idle = idle_mode(idle_spin, latency.held_us, latency.driver, fifo=priority > 0)
    try:
        spinners = IdleSpinners(rest_s=idle_spin_rest_ms * 1e-3) if idle == SPIN else None
        with spinners or contextlib.nullcontext():
            out = _measure(seconds, priority, period_s, deadline_fraction)
        return {**out, "cpu_latency_us": latency.held_us, "idle_cpus": idle,
                "idle_spin_rest_ms": idle_spin_rest_ms if spinners else None}
    finally:
        latency.close()


def _measure(seconds: float, priority: int, period_s: float, deadline_fraction: float) -> dict:
    steps = max(1, int(round(seconds / period_s)))
    cmd = [sys.executable, "-m", "hil.benchmarks.idle_loop", "--child", repr(period_s), str(steps),
           str(priority), repr(deadline_fraction * period_s)]
    outs = run_together([cmd] * NODES, "idle loop: a pacing process")      # both ready before t0 is chosen
    missed = sorted(set().union(*(o["missed"] for o in outs)))
    stalls = []                                      # runs of consecutive missed periods: one stall each
    for k in missed:
        if stalls and stalls[-1][1] == k - 1:
            stalls[-1][1] = k
        else:
            stalls.append([k, k])
    grants = [o["sched_fifo_granted"] for o in outs]
    return {"seconds": seconds, "steps": steps, "missed": len(missed),
            "missed_per_10k": len(missed) * 1e4 / steps, "stalls": len(stalls),
            "longest_stall_periods": max((b - a + 1 for a, b in stalls), default=0),
            "late_p99_us": max(o["late_p99_us"] for o in outs), "late_max_us": max(o["late_max_us"] for o in outs),
            "sched_fifo_granted": None if priority <= 0 else all(grants), "loadavg_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv and argv[0] == "--child":
        period_s, steps, priority, deadline_s = argv[1:5]
        _child(float(period_s), int(steps), int(priority), float(deadline_s))
        return 0
    p = argparse.ArgumentParser(prog="python -m hil.benchmarks.idle_loop", description=__doc__.split("\n\n")[0])
    p.add_argument("seconds", type=float)
    p.add_argument("--priority", type=int, default=0, help="SCHED_FIFO priority (0: normal scheduling)")
    p.add_argument("--cpu-latency-us", type=int, default=-1,
                   help="hold this CPU latency request meanwhile (hil/rt/cpu_latency.py; -1: none)")
    p.add_argument("--idle-spin", choices=("auto", "on", "off"), default="off",
                   help="idle spinners meanwhile, as [bus] idle_spin (hil/rt/idle_spin.py; default off)")
    p.add_argument("--idle-spin-rest-ms", type=float, default=5.0)
    a = p.parse_args(argv)
    try:
        print(json.dumps({**measure(a.seconds, a.priority, cpu_latency_us=a.cpu_latency_us, idle_spin=a.idle_spin,
                                    idle_spin_rest_ms=a.idle_spin_rest_ms),
                          "kernel_preemption": kernel_preemption()}))
    except HilError as e:
        print(f"idle_loop: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
