"""The time the machine takes each CPU away from this system: a floor for real-time deadlines.

Why: on a virtual machine the hypervisor can stop a vCPU (to run another guest, or its own work on
the guest's behalf) without the guest's scheduler knowing (``steal`` in ``/proc/stat`` is meant to
count that time; it is printed beside the probe's own figures, which do not depend on it). A real-time period in which the CPU that the plant or the TCU runs on is gone for
most of the period is missed by any program; this probe measures how often that happens, in the
same minutes as the real-time runs (``hil bench bus``).

How: one process per CPU, pinned to it (``sched_setaffinity``) at normal priority (a SCHED_FIFO
spinner would be stopped by the kernel's real-time throttling, 50 ms a second), reads the
monotonic clock in a tight loop for ``seconds`` (``hil.rt.idle_spin.spin``: a gap between two reads
with no context switch of the spinner is time *away*, the hypervisor holding the vCPU or interrupt
handlers running; one with a switch is this system's own scheduler, *guest*).

Figures: per CPU the away gaps (count, total, longest, and the 10 longest with their start), how
many were of at least ``LONG_AWAY_S`` and the largest share of those that end at one point of a
100 ms cycle (``cycle_share``: near 1 when a host's CPU quota stops the vCPU until its next period),
the guest gaps (count, total, longest), and the change of ``steal``; merged over the periods
``[t0 + k * period_s, t0 + (k + 1) * period_s)`` shared by both processes: ``periods_away``, the
periods in which some CPU was away for at least ``deadline_fraction`` of the period (the deadline's
share: what is left is shorter than a round trip), per 10 000 periods.

It is a floor in this sense only: a process needs the CPU it is on in every period (the plant and
the TCU both do), and a task on a vCPU the hypervisor holds cannot run elsewhere meanwhile, so a
period away is a missed deadline when the loop's process sits on that CPU; with two processes on
two CPUs it nearly always does. The probe cannot run beside a real-time run (it takes both CPUs),
so it measures the machine's minute, not the run's.

Beside a run the same measure comes from the run's own idle spinners (``hil.rt.idle_spin``: the same
loop at ``SCHED_IDLE``, in the time the run leaves idle), which also find the run's missed periods
that coincide with a CPU away. With ``rest_s`` each spinner rests as the run's idle spinners do
(``hil.rt.idle_spin``: on a host that caps the VM's CPU time near its vCPU count, spinners that never
rest exhaust the cap and measure the stalls they cause themselves); a rest is not observed.

``python -m hil.benchmarks.vcpu_away SECONDS`` prints the result as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from ..errors import HilError
from ..rt.idle_spin import CYCLE_S, GAP_S, spin
from .together import run_together

#: an away gap this long counts in ``cycle_share``
LONG_AWAY_S = 300e-6
#: the longest away gaps kept per CPU, with their start
LONGEST_KEPT = 10


def _child(cpu: int, seconds: float, rest_s: float, first_rest_s: float) -> None:
    os.sched_setaffinity(0, {cpu})
    print("ready", flush=True)
    t0 = float(sys.stdin.readline())
    gaps, turns = spin(t0, seconds, rest_s=rest_s, first_rest_s=first_rest_s)
    print(json.dumps({"cpu": cpu, "gaps": gaps, "turns": turns}))


def _steal_ticks() -> dict[str, int]:
    """Per CPU the ``steal`` column of ``/proc/stat`` (clock ticks); empty where there is none."""
    try:
        lines = open("/proc/stat").read().splitlines()
    except OSError:  # no /proc/stat (not Linux): no steal figures
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


def cycle_share(gaps, cycle_s: float = CYCLE_S, within_s: float = 1e-3, min_s: float = LONG_AWAY_S) -> float | None:
    """The largest share of the away gaps ``(start, length)`` of at least ``min_s`` whose ends fall
    within ``within_s`` of one point of a ``cycle_s`` cycle (None: no such gaps).  Near 1: they end
    together at the same point of every cycle, as when a host's CPU quota runs out and the next
    period of it begins; a machine that takes CPUs away at random gives about ``2 * within_s / cycle_s``."""
    ends = [(a + d) % cycle_s for a, d in gaps if d >= min_s]
    if not ends:
        return None
    near = max(sum(1 for f in ends if min(abs(e - f), cycle_s - abs(e - f)) <= within_s) for e in ends)
    return near / len(ends)


def measure(seconds: float, period_s: float = 1e-3, deadline_fraction: float = 0.9,
            cpus: list[int] | None = None, rest_s: float = 0.0) -> dict:
    """Spin on each of ``cpus`` (default: every CPU this process may use) for ``seconds``, resting
    ``rest_s`` per ``hil.rt.idle_spin.CYCLE_S`` (staggered, as the idle spinners); the figures of the
    module docstring."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None else cpus
    cmd = [sys.executable, "-m", "hil.benchmarks.vcpu_away", "--child"]
    steal0 = _steal_ticks()
    outs = run_together([cmd + [str(c), repr(seconds), repr(rest_s), repr(CYCLE_S * i / len(cpus))]
                         for i, c in enumerate(cpus)], "vCPU probe: a spinning process")
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
                        "long_away_gaps": sum(1 for a, d in mine if d >= LONG_AWAY_S),
                        "long_away_cycle_share": cycle_share(mine),
                        "longest_away": [{"at_s": a, "us": 1e6 * d}
                                         for a, d in sorted(mine, key=lambda g: -g[1])[:LONGEST_KEPT]],
                        "guest_gaps": len(theirs), "guest_ms": 1e3 * sum(theirs),
                        "longest_guest_us": 1e6 * max(theirs, default=0.0),
                        "steal_ms": (steal1[name] - steal0[name]) * tick_ms
                        if name in steal0 and name in steal1 else None})
    periods = max(1, int(round(seconds / period_s)))
    hit = periods_away(away, period_s, deadline_fraction)
    return {"seconds": seconds, "period_s": period_s, "deadline_fraction": deadline_fraction, "gap_us": GAP_S * 1e6,
            "rest_ms": 1e3 * rest_s,
            "periods": periods, "periods_away": len(hit), "periods_away_per_10k": len(hit) * 1e4 / periods,
            "cpus": per_cpu, "loadavg_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        _child(int(argv[1]), float(argv[2]), float(argv[3]), float(argv[4]))
        return 0
    p = argparse.ArgumentParser(prog="python -m hil.benchmarks.vcpu_away", description=__doc__.split("\n\n")[0])
    p.add_argument("seconds", type=float)
    p.add_argument("--period-s", type=float, default=1e-3)
    p.add_argument("--deadline-fraction", type=float, default=0.9)
    p.add_argument("--rest-ms", type=float, default=0.0,
                   help="each spinner rests this long every 100 ms, as the idle spinners (default 0: never)")
    a = p.parse_args(argv)
    try:
        print(json.dumps(measure(a.seconds, a.period_s, a.deadline_fraction, rest_s=a.rest_ms * 1e-3)))
    except HilError as e:
        print(f"vcpu_away: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
