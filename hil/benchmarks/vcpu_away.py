"""The time the machine takes each CPU away from this system: a floor for real-time deadlines.

Why: on a virtual machine the hypervisor can stop a vCPU (to run another guest, or its own work on
the guest's behalf) without the guest's scheduler knowing (``steal`` in ``/proc/stat`` is meant to
count that time; it is printed beside the probe's own figures, which do not depend on it). A real-time period in which the CPU that the plant or the TCU runs on is gone for
most of the period is missed by any program; this probe measures how often that happens, in the
same minutes as the real-time runs (``hil bench bus``).

How: one process per CPU, pinned to it (``sched_setaffinity``) at normal priority (a SCHED_FIFO
spinner would be stopped by the kernel's real-time throttling, 50 ms a second), reads the
monotonic clock in a tight loop for ``seconds``. Two consecutive reads more than ``GAP_S`` apart are
a *gap*. Each turn also reads the process's context switches (``getrusage``): a gap across which
the count grew is this system's own scheduler running something else (*guest*); one across which
it did not is time the CPU ran nothing of this system's processes, not even its scheduler: the
hypervisor held the vCPU, or interrupt handlers did (*away*).

Figures: per CPU the away gaps (count, total, longest, and the 10 longest with their start), the
guest gaps (count, total, longest), and the change of ``steal``; merged over the periods
``[t0 + k * period_s, t0 + (k + 1) * period_s)`` shared by both processes: ``periods_away``, the
periods in which some CPU was away for at least ``deadline_fraction`` of the period (the deadline's
share: what is left is shorter than a round trip), per 10 000 periods.

It is a floor in this sense only: a process needs the CPU it is on in every period (the plant and
the TCU both do), and a task on a vCPU the hypervisor holds cannot run elsewhere meanwhile, so a
period away is a missed deadline when the loop's process sits on that CPU; with two processes on
two CPUs it nearly always does. The probe cannot run beside a real-time run (it takes both CPUs),
so it measures the machine's minute, not the run's.

Beside a run (``Beside``): the same spinners at ``SCHED_IDLE`` run for as long as a real-time run,
taking only the time its processes leave idle; they see the absences that fall in that time (most of
it: the loop's processes sleep most of each period), and ``misses_with_cpu_away`` finds the run's
missed periods that coincide with one. This costs the run: its processes now preempt a spinner instead
of waking an idle CPU (``hil bench bus`` prints the round trip, to be compared with a run without).

``python -m hil.benchmarks.vcpu_away SECONDS`` prints the result as JSON.
"""
from __future__ import annotations

import argparse
import bisect
import json
import os
import resource
import signal
import subprocess
import sys
import time

from ..errors import HilError
from .together import run_together

#: two clock reads further apart than this are a gap (far longer than a turn of the loop)
GAP_S = 100e-6
#: the longest away gaps kept per CPU, with their start
LONGEST_KEPT = 10


def spin(t0: float, seconds: float, gap_s: float = GAP_S, stop: list | None = None) -> tuple[list, int]:
    """Read the clock from ``t0`` for ``seconds`` (or until ``stop`` is not empty); the gaps
    ``(start - t0, length, guest)`` and the turns.

    Turn i reads the clock (c_i), then the context switches (u_i). A switch inside the gap
    (c_{i-1}, c_i) may land before or after u_{i-1}, but always after u_{i-2} and before u_i: the gap
    is the guest's when u_i != u_{i-2} (a switch just outside the gap may count it as the guest's too:
    this errs towards "guest", never towards "away")."""
    clock, usage, me = time.perf_counter, resource.getrusage, resource.RUSAGE_SELF
    stop = [] if stop is None else stop
    while clock() < t0:
        pass
    end = t0 + seconds
    r = usage(me)
    before = switches = r.ru_nvcsw + r.ru_nivcsw          # u_{i-2}, u_{i-1}
    last = clock()
    gaps, turns = [], 0
    while last < end and not stop:
        now = clock()
        r = usage(me)
        s = r.ru_nvcsw + r.ru_nivcsw
        turns += 1
        if now - last > gap_s:
            gaps.append((last - t0, now - last, s != before))
        last, before, switches = now, switches, s
    return gaps, turns


def _child(cpu: int, seconds: float) -> None:
    os.sched_setaffinity(0, {cpu})
    print("ready", flush=True)
    t0 = float(sys.stdin.readline())
    gaps, turns = spin(t0, seconds)
    print(json.dumps({"cpu": cpu, "gaps": gaps, "turns": turns}))


def _child_beside(cpu: int) -> None:
    """A spinner beside a run: SCHED_IDLE, pinned, from "ready" until SIGTERM; prints its start and gaps."""
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    stop: list = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    t0 = time.perf_counter()
    print("ready", flush=True)
    gaps, turns = spin(t0, float("inf"), stop=stop)
    print(json.dumps({"cpu": cpu, "t0": t0, "gaps": gaps, "turns": turns}))


class Beside:
    """``with Beside(): ...``: one SCHED_IDLE spinner per CPU while the block runs (module docstring).

    After the block: ``away`` (CPU -> ``[(start, length)]``, start on ``time.perf_counter``) and
    ``figures`` (per CPU the away gaps, total and longest)."""

    def __init__(self, cpus: list[int] | None = None):
        self.cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
        self.children: list = []
        self.away: dict[int, list] = {}
        self.figures: list[dict] = []

    def __enter__(self):
        cmd = [sys.executable, "-m", "hil.benchmarks.vcpu_away", "--beside"]
        self.children = [subprocess.Popen(cmd + [str(c)], stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
                         for c in self.cpus]
        for child in self.children:
            if child.stdout.readline().strip() != "ready":
                self._kill()
                raise HilError(f"vCPU probe: a spinner beside the run did not start (exit {child.wait()})")
        return self

    def __exit__(self, *exc):
        outs = []
        try:
            for child in self.children:
                child.send_signal(signal.SIGTERM)
            for child in self.children:
                out = child.stdout.read()
                if child.wait() != 0:
                    raise HilError(f"vCPU probe: a spinner beside the run exited {child.returncode}")
                outs.append(json.loads(out))
        finally:
            self._kill()
        for o in outs:
            mine = [(o["t0"] + a, d) for a, d, guest in o["gaps"] if not guest]
            self.away[o["cpu"]] = mine
            self.figures.append({"cpu": o["cpu"], "away_gaps": len(mine), "away_ms": 1e3 * sum(d for a, d in mine),
                                 "longest_away_us": 1e6 * max((d for a, d in mine), default=0.0)})
        return False

    def _kill(self) -> None:
        for child in self.children:
            if child.poll() is None:
                child.kill()
                child.wait()


def misses_with_cpu_away(missed_steps, t0: float, period_s: float, deadline_fraction: float,
                         away: dict[int, list], min_away_s: float) -> list[int]:
    """The missed periods k during which one CPU was away for at least ``min_away_s`` in total between
    half a period before the period's start ``t0 + k * period_s`` and its deadline (an absence just
    before the start delays the plant's sensor frame; one after it, the TCU's answer)."""
    cpus = [(sorted(gaps), max((d for g, d in gaps), default=0.0)) for gaps in away.values()]
    starts = [[g for g, d in gaps] for gaps, longest in cpus]
    out = []
    for k in missed_steps:
        a = t0 + (k - 0.5) * period_s
        b = t0 + (k + deadline_fraction) * period_s
        for (gaps, longest), st in zip(cpus, starts):
            near = gaps[bisect.bisect_left(st, a - longest):bisect.bisect_right(st, b)]
            if sum(max(0.0, min(b, g + d) - max(a, g)) for g, d in near) >= min_away_s:
                out.append(k)
                break
    return out


def _steal_ticks() -> dict[str, int]:
    """Per CPU the ``steal`` column of ``/proc/stat`` (clock ticks); empty where there is none."""
    try:
        lines = open("/proc/stat").read().splitlines()
    except OSError:
        return {}
    return {f[0]: int(f[8]) for f in (line.split() for line in lines)
            if f and f[0].startswith("cpu") and f[0] != "cpu" and len(f) > 8}


def periods_away(away: dict[int, list], period_s: float, fraction: float) -> list[int]:
    """The periods k in which some CPU's away gaps ``(start, length)`` cover at least ``fraction`` of
    ``[k * period_s, (k + 1) * period_s)``."""
    hit = set()
    for gaps in away.values():
        covered: dict[int, float] = {}
        for a, d in gaps:
            b, k = a + d, int(a // period_s)
            while k * period_s < b:
                covered[k] = covered.get(k, 0.0) + min(b, (k + 1) * period_s) - max(a, k * period_s)
                k += 1
        hit.update(k for k, v in covered.items() if v >= fraction * period_s)
    return sorted(hit)


def measure(seconds: float, period_s: float = 1e-3, deadline_fraction: float = 0.9,
            cpus: list[int] | None = None) -> dict:
    """Spin on each of ``cpus`` (default: every CPU this process may use) for ``seconds``; the figures
    of the module docstring."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    cmd = [sys.executable, "-m", "hil.benchmarks.vcpu_away", "--child"]
    steal0 = _steal_ticks()
    outs = run_together([cmd + [str(c), repr(seconds)] for c in cpus], "vCPU probe: a spinning process")
    steal1 = _steal_ticks()
    tick_ms = 1e3 / os.sysconf("SC_CLK_TCK")
    per_cpu, away = [], {}
    for o in outs:
        mine = [(a, d) for a, d, guest in o["gaps"] if not guest]
        theirs = [d for a, d, guest in o["gaps"] if guest]
        away[o["cpu"]] = mine
        name = f"cpu{o['cpu']}"
        per_cpu.append({"cpu": o["cpu"], "turns_per_s": o["turns"] / seconds,
                        "away_gaps": len(mine), "away_ms": 1e3 * sum(d for a, d in mine),
                        "longest_away_us": 1e6 * max((d for a, d in mine), default=0.0),
                        "longest_away": [{"at_s": a, "us": 1e6 * d}
                                         for a, d in sorted(mine, key=lambda g: -g[1])[:LONGEST_KEPT]],
                        "guest_gaps": len(theirs), "guest_ms": 1e3 * sum(theirs),
                        "longest_guest_us": 1e6 * max(theirs, default=0.0),
                        "steal_ms": (steal1[name] - steal0[name]) * tick_ms
                        if name in steal0 and name in steal1 else None})
    periods = max(1, int(round(seconds / period_s)))
    hit = periods_away(away, period_s, deadline_fraction)
    return {"seconds": seconds, "period_s": period_s, "deadline_fraction": deadline_fraction, "gap_us": GAP_S * 1e6,
            "periods": periods, "periods_away": len(hit), "periods_away_per_10k": len(hit) * 1e4 / periods,
            "cpus": per_cpu, "loadavg_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        _child(int(argv[1]), float(argv[2]))
        return 0
    if argv and argv[0] == "--beside":
        _child_beside(int(argv[1]))
        return 0
    p = argparse.ArgumentParser(prog="python -m hil.benchmarks.vcpu_away", description=__doc__.split("\n\n")[0])
    p.add_argument("seconds", type=float)
    p.add_argument("--period-s", type=float, default=1e-3)
    p.add_argument("--deadline-fraction", type=float, default=0.9)
    a = p.parse_args(argv)
    try:
        print(json.dumps(measure(a.seconds, a.period_s, a.deadline_fraction)))
    except HilError as e:
        print(f"vcpu_away: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
