"""The vCPU probe (``hil.benchmarks.vcpu_away``): gaps in a spinning process, told apart by whether
this system's scheduler switched it out, and the periods they cover."""
import json
import os
import random
import signal
import subprocess
import sys
import time

from hil.benchmarks.vcpu_away import cycle_share, measure, periods_away

from .conftest import ROOT, case_seed, subprocess_env


def test_periods_away_sums_one_cpus_gaps_within_a_period_but_never_across_cpus():
    period = 1e-3
    away = {0: [(0.0101, 0.0004), (0.0106, 0.0003),     # period 10: 0.4 + 0.3 ms = 0.7 ms
                (0.0205, 0.0030)],                      # periods 20 (0.5 ms), 21, 22 (whole), 23 (0.5 ms)
            1: [(0.0100, 0.0002)]}                      # period 10 on the other CPU: not added to cpu0's
    assert periods_away(away, period, 0.65) == [10, 21, 22]
    assert periods_away(away, period, 0.45) == [10, 20, 21, 22, 23]
    assert periods_away(away, period, 0.95) == [21, 22]
    assert periods_away({0: [], 1: []}, period, 0.5) == []


def test_a_process_stopped_by_the_kernel_is_a_guest_gap_not_time_away():
    """SIGSTOP takes the spinner off its CPU through this system's scheduler: the gap across the stop
    is as long as the stop and is counted as the guest's, never as the machine's."""
    stop_ms = random.Random(case_seed("stop")).randrange(15, 40)
    print(f"stop {stop_ms} ms")
    child = subprocess.Popen([sys.executable, "-m", "hil.benchmarks.vcpu_away", "--child", "0", "1.0", "0", "0"],
                             cwd=ROOT, env=subprocess_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        t0 = time.perf_counter() + 0.05
        child.stdin.write(f"{t0!r}\n")
        child.stdin.close()
        time.sleep(0.4)
        stopped_at = time.perf_counter() - t0
        os.kill(child.pid, signal.SIGSTOP)
        time.sleep(stop_ms * 1e-3)
        os.kill(child.pid, signal.SIGCONT)
        out = json.loads(child.stdout.read())
    finally:
        if child.poll() is None:
            child.kill()
        child.wait()
    assert child.returncode == 0 and out["cpu"] == 0 and out["turns"] > 1000
    # the stop begins a little after stopped_at (the signal is delivered) and lasts about stop_ms
    (gap,) = [g for g in out["gaps"] if stopped_at - 1e-3 <= g[0] <= stopped_at + 5e-3 and g[1] >= 5e-3]
    start, length, guest = gap
    print("gap across the stop", gap)
    assert guest is True
    assert length >= (stop_ms - 1) * 1e-3
    assert all(a >= 0 and d > 1e-4 for a, d, g in out["gaps"])


def test_measure_merges_one_spinner_per_cpu():
    f = measure(0.5)
    cpus = sorted(os.sched_getaffinity(0))
    assert [c["cpu"] for c in f["cpus"]] == cpus
    assert f["periods"] == 500 and 0 <= f["periods_away"] <= 500
    assert f["periods_away_per_10k"] == f["periods_away"] * 1e4 / 500
    for c in f["cpus"]:
        print(c)
        assert c["turns_per_s"] > 1e4
        # a period counted away was >= 90 % covered by this CPU's away gaps: their total bounds the count
        assert c["away_ms"] >= 0 and c["longest_away_us"] <= 1e3 * c["away_ms"] + 1e-6
        assert len(c["longest_away"]) == min(c["away_gaps"], 10)
    assert f["periods_away"] <= sum(c["away_ms"] for c in f["cpus"]) / 0.9 + 1e-9


def test_cycle_share_tells_absences_that_end_together_each_cycle_from_scattered_ones():
    """Absences that end at the same point of a 100 ms cycle (a host's CPU quota running out) give a
    share near 1; absences at random points give about 2 ms / 100 ms; short ones do not count."""
    rng = random.Random(case_seed())
    cycle = 0.1
    together = [(k * cycle + 0.0437 - d, d) for k, d in
                ((rng.randrange(600), rng.uniform(0.4e-3, 2.5e-3)) for _ in range(40))]
    assert cycle_share(together) == 1.0
    scattered = [(rng.uniform(0, 60), rng.uniform(0.4e-3, 2.5e-3)) for _ in range(200)]
    assert cycle_share(scattered) < 0.15
    assert cycle_share(scattered + together) >= 40 / 240
    assert cycle_share([(1.0, 0.2e-3), (2.0, 0.1e-3)]) is None              # none of at least 0.3 ms
