"""``hil bench bus --realtime-runs``: real-time runs per bus, their medians and the lockstep speed."""
import json
import subprocess

import pytest

from .conftest import ROOT, case_seed, hil_command, subprocess_env

pytestmark = pytest.mark.realtime


def test_realtime_bench_lists_exit_codes_medians_and_whether_sched_fifo_was_granted(tmp_path):
    seed = case_seed() % 9999 + 1
    r = subprocess.run([*hil_command(), "bench", "bus", "--realtime-runs", "1", "--realtime-seconds", "1",
                        "--lockstep-seconds", "1", "--seed", str(seed), "--set", "bus.rt_priority=10", "--json",
                        "--doc", str(tmp_path), "--doc-name", "rt-check"],
                       cwd=ROOT, env=subprocess_env(), capture_output=True, text=True, timeout=170)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["default_bus"] in ("local", "hub") or out["default_bus"].startswith("socketcan")
    assert set(out["buses"]) == {"local", "hub", "inprocess"}
    for bus, b in out["buses"].items():
        assert {"runs", "exit_codes", "missed_per_10k", "jitter_p99_us", "round_trip_p99_us",
                "lockstep_speed"} <= set(b), bus
        assert len(b["runs"]) == 1 and b["exit_codes"] == [b["runs"][0]["exit_code"]]
        assert b["lockstep_speed"] > 0 and b["lockstep_speeds"] == [b["lockstep_speed"]]
        run = b["runs"][0]
        assert isinstance(run["sched_fifo_granted"], bool)      # asked for: granted or refused, never silent
        if run["exit_code"] == 0:
            assert 0 <= run["missed_per_10k"] <= 10_000 and run["jitter_p99_us"] >= 0
        print(bus, run)
    # the targets, each judged or said to be unmeasured, in the JSON and in the document the bench wrote
    targets = {t["target"]: t for t in out["targets"]}
    speed = out["buses"]["inprocess"]["lockstep_speeds"][0]
    (inproc,) = [t for name, t in targets.items() if name.startswith("inprocess lockstep >= 8x")]
    assert inproc["met"] == (speed >= 8.0)
    fifo = out["buses"]["local"]["runs"][0]["sched_fifo_granted"]
    assert any(t["met"] is None for t in out["targets"]) == (not fifo)
    # the idle loop of the same round
    (idle,) = out["idle_loop"]
    assert idle["steps"] == 1000 and 0 <= idle["missed"] <= 1000 and isinstance(idle["sched_fifo_granted"], bool)
    # the vCPU probe of the same round, and the missed-deadline target reports its floor
    for bus, b in out["buses"].items():        # the spinners beside each run, placed by the run's t0_monotonic_s
        run = b["runs"][0]
        if run["exit_code"] == 0:
            v = run["vcpu_probe"]
            assert 0 <= v["missed_with_cpu_away_per_10k"] <= run["missed_per_10k"], (bus, v)
            assert len(v["cpus"]) >= 1 and all(c["away_ms"] >= 0 for c in v["cpus"])
            assert run["idle_cpus"] == "spin" and run["idle_spin_rest_ms"] == 5.0   # the probe turns them on
    (probe,) = out["vcpu_away"]
    assert probe["periods"] == 1000 and 0 <= probe["periods_away"] <= 1000 and len(probe["cpus"]) >= 1
    assert probe["rest_ms"] == 5.0                               # resting as the runs' spinners do
    for c in probe["cpus"]:
        assert 0 <= c["long_away_gaps"] <= c["away_gaps"]
        assert (c["long_away_cycle_share"] is None) == (c["long_away_gaps"] == 0)
    if fifo:
        (missed,) = [t for name, t in targets.items() if "missed per 10 000" in name]
        assert f"{probe['periods_away_per_10k']:.1f}" in missed["measured"] and "vCPU probe" in missed["measured"]
    doc = (tmp_path / "rt-check.md").read_text()
    assert "## An idle loop in the same minutes" in doc
    assert "## The machine's floor: CPUs taken away (vCPU probe)" in doc
    assert not (tmp_path / "realtime.md").exists()          # --doc-name names the files
    assert json.loads((tmp_path / "rt-check.json").read_text())["targets"] == out["targets"]
    assert "| target | measured |" in doc and f"{speed:.2f}x" in doc
