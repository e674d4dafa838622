"""The period's account (``hil.period_account``) and ``hil bench period``: exclusive times per part and per
period, on a clock that advances by known steps; and the bench on a real two-process run."""
import json
import subprocess
import sys

import pytest

import hil.period_account as pa

from .conftest import ROOT, subprocess_env


class Clock:
    """``perf_counter_ns`` that advances by ``step`` ns at each read."""

    def __init__(self, step: int = 100):
        self.t, self.step = 0, step

    def __call__(self) -> int:
        self.t += self.step
        return self.t


def test_nested_parts_count_once_each_and_periods_apart(monkeypatch):
    account = pa.PeriodAccount(("outer", "inner", "collector"), 4)
    clock = Clock()
    monkeypatch.setattr(pa.time, "perf_counter_ns", clock)
    account.overhead_ns = 0.0

    def inner():
        clock.t += 1000                       # the inner part's own work
        return "in"

    def outer():
        clock.t += 5000                       # the outer part's own work
        return wrapped_inner() + "-out"

    wrapped_inner = account.timed(inner, "inner")
    wrapped_outer = account.timed(outer, "outer")
    wrapped_outer()                           # before the first period: counted nowhere
    account.begin_period(clock())
    assert wrapped_outer() == "in-out"
    wrapped_inner()
    account.begin_period(clock())
    wrapped_inner()
    account.begin_period(clock())
    parts, names, total = account.table(skip=0)
    assert names == ["outer", "inner", "collector", "the account itself", "other"]
    assert len(total) == 2
    # period 0: the inner part twice (its work and the clock step of its closing read), the outer part its work,
    # the inner wrapper's opening read and its own closing read (a wrapper's lines are charged to its caller)
    inner_each = 1000 + 100
    outer_own = 5000 + 100 + 100
    assert parts[0, 1] == pytest.approx(2 * inner_each / 1e3)
    assert parts[0, 0] == pytest.approx(outer_own / 1e3)
    assert parts[1, 1] == pytest.approx(inner_each / 1e3) and parts[1, 0] == 0.0
    # the parts and the rest add up to the period, whatever the rest is
    assert parts.sum(axis=1) == pytest.approx(total)
    assert account.calls[0] == 3 and account.calls[1] == 1


@pytest.mark.slow
def test_bench_period_accounts_for_both_sides_of_a_two_process_run(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hil.cli", "bench", "period", "--seconds", "0.5", "--plant-seconds",
                        "0.2", "--json"], cwd=ROOT, capture_output=True, text=True, timeout=300, env=subprocess_env())
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    a = out["accounted"][0]
    assert set(a["plant"]["parts"]) == set(pa.PLANT_PARTS) | {"the account itself", "other"}
    assert set(a["tcu"]["parts"]) == set(pa.TCU_PARTS) | {"the account itself", "other"}
    assert a["plant"]["periods"] > 400 and a["tcu"]["periods"] > 400
    for side in ("plant", "tcu"):          # every period has its plant step or its reading's command
        key = "plant step" if side == "plant" else "command"
        assert a[side]["parts"][key]["median_us"] > 0
    assert all(v["median_us"] > 0 for v in a["transit"].values())
    assert out["plain"][0]["identified"] is not None and out["plant_alone"]["x_realtime"] > 0
