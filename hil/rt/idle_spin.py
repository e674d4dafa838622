"""Idle spinners: one ``SCHED_IDLE`` process per CPU for a real-time run, so that no vCPU halts
while the run waits, and so that the run sees the time the machine takes a CPU away.

Why spin.  Each frame of a real-time period wakes a process asleep in the bus (the TCU on the
sensor frame, the plant on the command). On a virtual machine an idle vCPU halts, and a halted vCPU
runs again only when the host schedules it: tens of microseconds, and on a busy host now and then
milliseconds. Where a cpuidle driver runs, the CPU latency request of ``hil.rt.cpu_latency`` makes idle
CPUs poll instead; where none does (``/sys/devices/system/cpu/cpuidle/current_driver`` reads
``none``), idle is a plain halt whatever is asked, and only a runnable task keeps a vCPU running. A
``SCHED_IDLE`` task is such a task that takes nothing from the run: it runs only when no other task
wants its CPU, and a waking task preempts it at once.

Why rest.  A host may cap a VM's CPU time (Linux CPU bandwidth control: a quota of CPU time per
period, 100 ms by default). With every vCPU kept busy, a VM whose quota is about its vCPU count runs
out of it before the period ends (the host's own work on its behalf counts too), and then all its
vCPUs stop until the next period begins: a stall of milliseconds at the same point of every
100 ms. So each spinner sleeps ``rest_s`` once every ``CYCLE_S``, the spinners staggered across the
cycle, handing that much time back. A rest must be a sleep long enough for the vCPU to really stop:
a vCPU that halts for a few tens of microseconds is polled by the host meanwhile, and charged.

Absences.  Each spinner reads the monotonic clock in a tight loop (``spin``). Two reads more than
``GAP_S`` apart are a gap; turn i reads the clock (c_i), then the process's context switches (u_i),
and the gap (c_{i-1}, c_i) is this system's own scheduler running something else when u_i differs
from u_{i-2}, the count read before the gap began (a switch just outside the gap may count it as the
guest's too: this errs towards "guest", never towards "away"). A gap with no switch is time no task
of this system ran on that CPU, not even its scheduler: the host held the vCPU, or interrupt
handlers ran (*away*). ``misses_with_cpu_away`` finds the missed periods that coincide with one.

The spinners end with the run: ``stop`` (SIGTERM, then their report), and the kernel kills them
when the process that started them dies (``PR_SET_PDEATHSIG``).
"""
from __future__ import annotations

import bisect
import contextlib
import json
import os
import resource
import signal
import subprocess
import sys
import time

from ..errors import HilError

#: two clock reads further apart than this are a gap (far longer than a turn of the loop)
GAP_S = 100e-6
#: the spinners' cycle: one rest per spinner in each (the default period of Linux CPU bandwidth control)
CYCLE_S = 0.1
#: a missed period "coincides with a CPU away" when one CPU was away for at least this share of a
#: period around it (``misses_with_cpu_away``)
AWAY_SHARE = 0.5
#: how the idle CPUs of a real-time run wait (``idle_mode``)
POLL, SHALLOW, SPIN, HALT = "poll", "shallow", "spin", "halt"


def idle_mode(setting: str, latency_held_us: int | None, driver: str | None, fifo: bool) -> str:
    """How the idle CPUs of a real-time run wait, from ``[bus] idle_spin`` (``setting``), the CPU
    latency request held (``hil.rt.cpu_latency``; None: none), the cpuidle driver (None: none) and
    whether the run's processes run SCHED_FIFO (``fifo``): SPIN with ``"on"``, or with ``"auto"``
    where no request is carried out (none held, or no driver to carry it out) and the run is
    SCHED_FIFO; else POLL (0 us held under a driver), SHALLOW (a larger bound) or HALT.

    Why only under SCHED_FIFO: a real-time task preempts a spinner at once, wherever it is; at normal
    priority a waking task preempts a ``SCHED_IDLE`` one at once only within their own group, and the
    TCU process runs in a session (an autogroup) of its own, so it can wait for the end of a
    spinner's slice."""
    polls = latency_held_us is not None and driver is not None
    if setting == "on" or (setting == "auto" and not polls and fifo):
        return SPIN
    if not polls:
        return HALT
    return POLL if latency_held_us == 0 else SHALLOW


def spin(t0: float, seconds: float, gap_s: float = GAP_S, stop: list | None = None, rest_s: float = 0.0,
         first_rest_s: float = 0.0) -> tuple[list, int]:
    """Read the clock from ``t0`` for ``seconds`` (or until ``stop`` is not empty); the gaps
    ``(start - t0, length, guest)`` (module docstring) and the turns.  With ``rest_s``: sleep that
    long at ``t0 + first_rest_s`` and every ``CYCLE_S`` after; a rest is no gap."""
    clock, usage, me = time.perf_counter, resource.getrusage, resource.RUSAGE_SELF
    stop = [] if stop is None else stop
    while clock() < t0:
        pass
    end = t0 + seconds
    next_rest = t0 + first_rest_s if rest_s > 0.0 else float("inf")
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
        if now >= next_rest:
            time.sleep(rest_s)
            while next_rest <= clock():
                next_rest += CYCLE_S
            r = usage(me)
            before = switches = r.ru_nvcsw + r.ru_nivcsw
            last = clock()
    return gaps, turns


def _die_with_parent(parent: int) -> None:
    """SIGKILL from the kernel when the parent dies (``PR_SET_PDEATHSIG``); already gone: exit now."""
    with contextlib.suppress(OSError, AttributeError):
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(0)


def _child(cpu: int, rest_s: float, first_rest_s: float, parent: int) -> None:
    """One spinner: pinned to ``cpu``, SCHED_IDLE, from "ready" until SIGTERM; prints its start, its
    away gaps (start, length) and how many gaps were the guest's."""
    _die_with_parent(parent)
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    stop: list = []
    signal.signal(signal.SIGTERM, lambda signum, frame: stop.append(signum))
    signal.signal(signal.SIGINT, signal.SIG_IGN)          # a Ctrl-C reaches the group; the run decides
    t0 = time.perf_counter()
    print("ready", flush=True)
    gaps, turns = spin(t0, float("inf"), stop=stop, rest_s=rest_s, first_rest_s=first_rest_s)
    print(json.dumps({"cpu": cpu, "t0": t0, "away": [(a, d) for a, d, guest in gaps if not guest],
                      "guest_gaps": sum(1 for g in gaps if g[2]), "turns": turns}))


class IdleSpinners:
    """``with IdleSpinners(cpus, rest_s): ...``: one spinner per CPU of ``cpus`` (default: every CPU
    this process may use) while the block runs, each resting ``rest_s`` per ``CYCLE_S``, staggered.

    After the block: ``away`` (CPU -> ``[(start, length)]``, start on ``time.perf_counter``) and
    ``figures`` (per CPU the away gaps, their total and the longest).  ``HilError`` when a spinner
    does not start or does not report."""

    def __init__(self, cpus: list[int] | None = None, rest_s: float = 0.0):
        self.cpus = sorted(os.sched_getaffinity(0)) if cpus is None else list(cpus)
        self.rest_s = rest_s
        self.children: list = []
        self.away: dict[int, list] = {}
        self.figures: list[dict] = []

    def start(self) -> "IdleSpinners":
        n = max(len(self.cpus), 1)
        try:
            for i, cpu in enumerate(self.cpus):
                cmd = [sys.executable, "-m", "hil.rt.idle_spin", str(cpu), repr(self.rest_s), repr(CYCLE_S * i / n),
                       str(os.getpid())]
                # in this process's session: with autogroup scheduling a session of its own would be a
                # group of its own, weighed as much as the run's whatever the spinner's policy
                self.children.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                                      text=True))
            for child in self.children:
                if child.stdout.readline().strip() != "ready":
                    raise HilError(f"idle spinner: a spinner did not start (exit {child.wait()})")
        except (OSError, HilError):
            self.kill()
            raise
        return self

    def stop(self) -> None:
        """End the spinners and take their reports."""
        outs = []
        try:
            for child in self.children:
                with contextlib.suppress(ProcessLookupError):
                    child.send_signal(signal.SIGTERM)
            for child in self.children:
                out = child.stdout.read()
                if child.wait() != 0:
                    raise HilError(f"idle spinner: a spinner exited {child.returncode}")
                outs.append(json.loads(out))
        finally:
            self.kill()
        for o in outs:
            mine = [(o["t0"] + a, d) for a, d in o["away"]]
            self.away[o["cpu"]] = mine
            self.figures.append({"cpu": o["cpu"], "away_gaps": len(mine), "away_ms": 1e3 * sum(d for a, d in mine),
                                 "longest_away_us": 1e6 * max((d for a, d in mine), default=0.0)})

    def summary(self, missed_steps, t0: float, period_s: float, deadline_fraction: float) -> dict:
        """After ``stop``: the run's summary fields: per CPU the time away (``cpu_away``) and the missed
        periods that coincide with a CPU away for ``AWAY_SHARE`` of a period
        (``missed_deadlines_cpu_away``)."""
        hit = misses_with_cpu_away(missed_steps, t0, period_s, deadline_fraction, self.away, AWAY_SHARE * period_s)
        return {"idle_spin_rest_ms": 1e3 * self.rest_s, "cpu_away": self.figures, "missed_deadlines_cpu_away": len(hit)}

    def kill(self) -> None:
        """End the spinners at once, reports lost (a failing run)."""
        for child in self.children:
            if child.poll() is None:
                child.kill()
                child.wait()
            if child.stdout is not None:
                child.stdout.close()
        self.children = []

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        if exc[0] is None:
            self.stop()
        else:
            self.kill()
        return False


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


if __name__ == "__main__":
    _child(int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]))
