"""An idle loop paced as the plant node (``hil.benchmarks.idle_loop``)."""
import random
import sys
import threading
import time

from hil.benchmarks.idle_loop import measure, pace

from .conftest import case_seed


def test_a_stall_of_the_pacing_loop_shows_as_late_wakes():
    """A thread holding the interpreter for ``stall_ms`` stalls the pacer as a descheduled CPU would:
    the periods it covers wake late by up to the stall, however quiet the machine."""
    stall_ms = random.Random(case_seed("stall")).randrange(15, 40)
    print(f"stall {stall_ms} ms")
    old = sys.getswitchinterval()
    sys.setswitchinterval(1.0)                 # the busy thread keeps the interpreter for its whole stall

    def busy():
        time.sleep(0.1)
        end = time.perf_counter() + stall_ms * 1e-3
        while time.perf_counter() < end:
            pass

    try:
        t = threading.Thread(target=busy)
        t0 = time.perf_counter() + 0.01
        t.start()
        late = pace(t0, 1e-3, 300)
        t.join()
    finally:
        sys.setswitchinterval(old)
    assert len(late) == 300
    missed = sum(x > 0.9e-3 for x in late)
    assert missed >= stall_ms - 3, (missed, stall_ms)
    assert max(late) >= (stall_ms - 2) * 1e-3


def test_two_paced_processes_merge_their_late_periods():
    f = measure(0.5)
    assert f["steps"] == 500
    assert 0 <= f["stalls"] <= f["missed"] <= 500
    assert f["missed_per_10k"] == f["missed"] * 1e4 / 500
    assert f["sched_fifo_granted"] is None         # not asked for
    assert f["late_max_us"] >= f["late_p99_us"] >= 0
