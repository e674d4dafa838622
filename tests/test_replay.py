"""``hil replay``: real ``hil run`` logs (two processes over the default bus) re-identified offline."""
import json
import subprocess

import pytest

from hil.loop import run_inprocess
from hil.scenario import load_scenario

from .conftest import SCENARIOS, hil_command, subprocess_env

PF_STRATEGY = "proposed"     # a particle-filter strategy (identifier/strategies/proposed.py)


def hil(*args, timeout=300):
    return subprocess.run(hil_command() + list(args), capture_output=True, text=True, env=subprocess_env(),
                          timeout=timeout)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """strategy -> (hil run --json summary, log path), both from `hil run` on its default bus."""
    out = tmp_path_factory.mktemp("runs")
    res = {}
    for strategy in ("nlls", PF_STRATEGY):
        r = hil("run", str(SCENARIOS / "ffcc_a.toml"), "--strategy", strategy, "--seed", "4", "--out", str(out),
                "--json")
        assert r.returncode == 0, r.stderr
        s = json.loads(r.stdout)
        res[strategy] = (s, out / f"ffcc_a-{strategy}-4.mcap")
    return res


@pytest.mark.parametrize("strategy", ["nlls", PF_STRATEGY])
def test_replay_reproduces_the_logged_identification(runs, strategy):
    run, path = runs[strategy]
    r = hil("replay", str(path), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["matches_log"] is True
    assert s["source"] == "mcap-frames"
    assert s["strategy"] == strategy and s["seed"] == 4
    # the same figures hil run printed
    for key in ("identified", "t_identified_s", "rt_percent", "params", "corrections", "samples", "t_serious_s",
                "t_detected_s", "mse", "r2", "peak_mu_err_percent"):
        assert s[key] == run[key], key
    assert s["messages_read"] == run["messages"]
    assert s["sensor_readings"] == 1000
    assert s["corrections"] >= 1 and s["identified"]


def test_another_strategy_on_the_same_run(runs):
    """The nlls run replayed with the PF strategy identifies what the PF run identified (same frames)."""
    pf_run, _ = runs[PF_STRATEGY]
    _, nlls_path = runs["nlls"]
    r = hil("replay", str(nlls_path), "--strategy", PF_STRATEGY, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["strategy"] == PF_STRATEGY
    assert s["matches_log"] is None          # not the logged strategy: nothing to match
    assert s["logged"]["strategy"] == "nlls"
    assert s["params"] == pf_run["params"] and s["t_identified_s"] == pf_run["t_identified_s"]


def test_text_output_reports_speed(runs):
    _, path = runs[PF_STRATEGY]
    r = hil("replay", str(path))
    assert r.returncode == 0, r.stderr
    line = [ln for ln in r.stdout.splitlines() if "samples/s" in ln]
    assert line and "matches the logged identification" in line[0], r.stdout
    assert float(line[0].split(" samples/s")[0].split()[-1]) > 0


def test_log_without_frames_replays_from_plant_sensor(tmp_path):
    """run_inprocess records no CAN frames: the replay reads /plant/sensor instead."""
    scenario = load_scenario(SCENARIOS / "ffcc_a.toml")
    run = run_inprocess(scenario, "nlls", seed=5, out_dir=tmp_path, progress=False)
    r = hil("replay", run["mcap"], "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["source"] == "mcap-sensor"
    assert s["matches_log"] is True
    assert s["params"] == run["params"] and s["corrections"] == run["corrections"]


def test_bad_strategy_is_one_line(runs):
    _, path = runs["nlls"]
    r = hil("replay", str(path), "--strategy", "nope")
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "unknown strategy 'nope'" in r.stderr
