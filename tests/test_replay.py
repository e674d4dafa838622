"""``hil replay``: real ``hil run`` logs (two processes over the default bus) re-identified offline."""
import json
from pathlib import Path

import pytest


from .conftest import ROOT, SCENARIOS, hil, kill_run_when_log_reaches, once_per_session

PF_STRATEGY = "proposed"     # a particle-filter strategy (identifier/strategies/proposed.py)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """strategy -> (hil run --json summary, log path), both from `hil run` on its default bus (made once
    per test session, ``once_per_session``)."""
    def make(out):
        res = {}
        for strategy in ("gp", PF_STRATEGY):
            r = hil("run", str(SCENARIOS / "ffcc_a.toml"), "--strategy", strategy, "--seed", "4", "--out", str(out),
                    "--json")
            assert r.returncode == 0, r.stderr
            res[strategy] = (json.loads(r.stdout), str(out / f"ffcc_a-{strategy}-4.mcap"))
        return res

    return {k: (s, Path(path)) for k, (s, path) in once_per_session(tmp_path_factory, "replay_runs", make).items()}


@pytest.mark.parametrize("strategy", ["gp", PF_STRATEGY])
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
    """The gp run replayed with the PF strategy identifies what the PF run identified (same frames)."""
    pf_run, _ = runs[PF_STRATEGY]
    _, gp_path = runs["gp"]
    r = hil("replay", str(gp_path), "--strategy", PF_STRATEGY, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["strategy"] == PF_STRATEGY
    assert s["matches_log"] is None          # not the logged strategy: nothing to match
    assert s["logged"]["strategy"] == "gp"
    assert s["params"] == pf_run["params"] and s["t_identified_s"] == pf_run["t_identified_s"]


def test_text_output_reports_speed(runs):
    _, path = runs[PF_STRATEGY]
    r = hil("replay", str(path))
    assert r.returncode == 0, r.stderr
    line = [ln for ln in r.stdout.splitlines() if "samples/s" in ln]
    assert line and "matches the logged identification" in line[0], r.stdout
    assert float(line[0].split(" samples/s")[0].split()[-1]) > 0


@pytest.mark.parametrize("name, source", [("ffcc_a-proposed-1-hub-7d64428.mcap", "mcap-frames"),
                                          ("ffcc_a-proposed-1-inprocess-7d64428.mcap", "mcap-sensor")])
def test_logs_recorded_before_the_redesign_replay_to_the_same_identification(name, source):
    """tests/data holds two logs written by commit 7d64428, before hil/ was redesigned (FFCC-a,
    proposed, seed 1, fault at 0.15 s, 0.25 s long): one over the hub with its CAN frames, one by the
    old in-process loop that recorded no frames (the replay then reads /plant/sensor).  Both must
    still replay to the identification they logged: same steps, kinds and corrections, parameters to
    1e-9 (the compiled kernels' last bits depend on the CPU class: 1 ulp between Zen 4 and Skylake)."""
    r = hil("replay", ROOT / "tests" / "data" / name, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["source"] == source
    assert s["matches_log"] is True
    assert s["corrections"] == s["logged"]["corrections"] == 2
    assert s["params"] == pytest.approx(s["logged"]["params"], rel=1e-9)
    assert s["rt_percent"] == pytest.approx(34.667, abs=0.01)


def test_a_closed_loop_identified_log_of_today_replays_the_same(tmp_path):
    """A wet-patch run with today's ``identified`` law (two changes of rail, so its drop and climb act and
    it asks for re-arms) replayed: the log marks today's behaviour in its run metadata, and the replay
    gives the logged identification, not a counterfactual one."""
    from mcap.reader import make_reader

    r = hil("run", str(SCENARIOS / "wet_patch.toml"), "--bus", "inprocess", "--set", "rail.1.start_s=0.4",
            "--set", "rail.2.start_s=1.5", "--set", "run.duration_s=2.5", "--out", str(tmp_path), "--json",
            "--no-rrd")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["tcu_rearms"] >= 1                 # the law's request reached the identifier
    path = Path(summary["mcap"])
    with open(path, "rb") as f:
        run = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["run"]
    assert {"identified_rail_climb", "identified_past_a_peak", "identified_rise", "identified_creep_bounds",
            "gp_rail_changes"} <= set(run)
    r = hil("replay", str(path), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["control"] == "identified" and s["counterfactual"] is False and s["matches_log"] is True


def test_a_gp_log_recorded_before_the_range_followed_the_data_replays_the_same():
    """tests/data/ffcc_a-gp-1-a2f9a38.mcap: ``hil run scenarios/ffcc_a.toml --seed 1 --set
    run.fault_time_s=0.15 --set run.duration_s=0.3`` by commit a2f9a38, whose ``gp`` gave up at a fixed
    3 km/h and whose TcuInterval had no IntervalOpen (48 bytes).  FFCC-a peaks at 1.27 km/h, below that
    bound, so the replay (the range that follows the data, the grid grown past 4 km/h) must give the
    identification it logged, with closed intervals."""
    r = hil("replay", ROOT / "tests" / "data" / "ffcc_a-gp-1-a2f9a38.mcap", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["strategy"] == "gp" and s["seed"] == 1 and s["matches_log"] is True
    assert s["identified"] and s["t_identified_s"] == s["logged"]["t_identified_s"] == 0.26
    assert s["corrections"] == s["logged"]["corrections"] == 21
    assert s["params"] == pytest.approx(s["logged"]["params"], rel=1e-9)
    assert s["peak_interval_open"] is False and 1.2 < s["peak_creep_ci"][0] < s["peak_creep_ci"][1] < 1.35


def test_a_closed_loop_gp_log_recorded_before_gp_dated_rail_changes_replays_the_same():
    """tests/data/wet_patch-gp-identified-1-f7678e9.mcap: ``hil run scenarios/wet_patch.toml --set
    rail.1.start_s=0.4 --set rail.2.start_s=1.5 --set run.duration_s=0.5`` by commit f7678e9, before
    ``gp`` dated a change of rail in closed loop: it confirmed at 0.418 s a peak creep 0.744 km/h, a point,
    on a wet rail peaking at 0.9 km/h.  Its run metadata has no ``gp_rail_changes`` and no
    ``identified_rail_climb``, so the replay runs gp and the law as they ran then (the law's requests to re-arm
    reach the identifier) and gives what it logged (today's gp, dating the change, confirms nothing there,
    and with today's law the replay did not match either)."""
    r = hil("replay", ROOT / "tests" / "data" / "wet_patch-gp-identified-1-f7678e9.mcap", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["control"] == "identified" and s["strategy"] == "gp" and s["counterfactual"] is False
    assert s["matches_log"] is True
    assert s["t_identified_s"] == s["logged"]["t_identified_s"] == 0.418
    assert s["params"] == pytest.approx(s["logged"]["params"], rel=1e-9)
    assert s["peak_creep_ci"] == pytest.approx([0.744, 0.744], abs=1e-3)


def test_bad_strategy_is_one_line(runs):
    _, path = runs["gp"]
    r = hil("replay", str(path), "--strategy", "nope")
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "unknown strategy 'nope'" in r.stderr


# -- damaged and foreign logs -------------------------------------------------------------------------------
def replay_in_process(capsys, *args):
    """The real ``hil`` entry point in this process (50 cuts x a fresh interpreter would cost minutes)."""
    from hil.cli import main

    capsys.readouterr()
    rc = main(["replay", *args])
    out, err = capsys.readouterr()
    return rc, out, err


def test_log_cut_at_50_byte_positions(runs, tmp_path, capsys):
    run, path = runs[PF_STRATEGY]
    data = path.read_bytes()
    n = len(data)
    # 10 fixed positions (inside the magic, the header, the metadata, the last bytes) + 40 spread over the file
    cuts = [0, 5, 9, 30, 200, 2000, n - 1, n - 9, n - 64, n - 2000] + [int(n * (i + 0.5) / 40) for i in range(40)]
    assert len(set(cuts)) == 50
    cut_path = tmp_path / "cut.mcap"
    recovered = []
    for c in sorted(cuts):
        cut_path.write_bytes(data[:c])
        rc, out, err = replay_in_process(capsys, str(cut_path), "--json")
        assert "Traceback" not in err
        if rc == 0:
            s = json.loads(out)
            assert err.count("\n") == 1 and "is damaged" in err and "recovered" in err, (c, err)
            assert s["messages_read"] > 0 and s["sensor_readings"] > 0
            assert s["messages_read"] <= run["messages"]
            # what the log still holds of the identification, the replay reproduces
            assert s["matches_log"] is True, c
            recovered.append((c, s["messages_read"], s["sensor_readings"]))
        else:
            assert rc == 2, (c, rc, err)
            assert err.count("\n") == 1 and err.startswith("hil replay: error: "), (c, err)
            assert c < 40_000, f"cut at {c} of {n} bytes gave nothing usable: {err}"
    # the 40 spread cuts recover more and more of the run; the last ones nearly all of it
    assert len(recovered) >= 40
    counts = [m for _, m, _ in recovered]
    assert counts == sorted(counts)
    assert recovered[-1][2] >= 990


def test_run_killed_with_sigkill_replays_up_to_the_kill(tmp_path):
    path = tmp_path / f"ffcc_a-{PF_STRATEGY}-1.mcap"
    kill_run_when_log_reaches(["run", str(SCENARIOS / "ffcc_a.toml"), "--strategy", PF_STRATEGY, "--out", str(tmp_path),
                               "--set", "run.duration_s=20"], path, 300_000)
    r = hil("replay", str(path), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert "is damaged" in r.stderr and "recovered" in r.stderr and "Traceback" not in r.stderr
    assert s["log_complete"] is False and s["sensor_readings"] > 300
    assert s["matches_log"] is True


def test_foreign_and_non_mcap_files_get_one_line(tmp_path, capsys):
    from mcap.writer import Writer

    foreign = tmp_path / "other_tool.mcap"
    with foreign.open("wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("Pose", "jsonschema", b"{}")
        cid = w.register_channel("/pose", "json", sid)
        for i in range(20):
            w.add_message(cid, i, json.dumps({"x": i}).encode(), i)
        w.finish()
    text = tmp_path / "notes.mcap"
    text.write_text("not a log\n")
    garbage_blf = tmp_path / "junk.blf"
    garbage_blf.write_bytes(bytes(range(256)) * 3)
    cases = [
        ((str(foreign),), "no scenario metadata"),
        ((str(foreign), "--scenario", str(SCENARIOS / "ffcc_a.toml")), "no sensor data"),
        ((str(text),), "not an MCAP file"),
        ((str(tmp_path / "missing.mcap"),), "No such file"),
        ((str(tmp_path),), "cannot read"),
        ((str(garbage_blf), "--scenario", str(SCENARIOS / "ffcc_a.toml")), "not a CAN log"),
        ((str(garbage_blf),), "--scenario"),
    ]
    for args, expected in cases:
        rc, out, err = replay_in_process(capsys, *args)
        assert rc == 2 and out == "", args
        assert err.count("\n") == 1 and expected in err, (args, err)


# -- CAN logs of other tools ----------------------------------------------------------------------------------
@pytest.mark.parametrize("suffix", ["log", "asc", "blf"])
def test_can_log_written_by_python_can_replays_the_same(runs, tmp_path, suffix):
    """The frames of a real run written with python-can's own writers (candump .log, Vector .asc, .blf)."""
    import can

    from hil.log.read import read_log

    run, path = runs["gp"]
    log = read_log(path, topics={"/can/frames"})
    can_log = tmp_path / f"rig.{suffix}"
    written = 0
    with can.Logger(str(can_log)) as writer:
        for _, _, m in log.messages:
            writer.on_message_received(can.Message(
                timestamp=m.wall_time_ns * 1e-9, arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id,
                is_fd=m.is_fd, bitrate_switch=m.bitrate_switch, dlc=m.dlc, data=bytes(m.data),
                is_rx=m.direction == "rx", channel="vcan0"))
            written += 1
    assert written > 2000
    r = hil("replay", str(can_log), "--scenario", str(SCENARIOS / "ffcc_a.toml"), "--seed", "4", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["source"] == "can-log" and s["messages_read"] == written
    for key in ("identified", "t_identified_s", "params", "corrections", "samples", "t_detected_s", "r2"):
        assert s[key] == run[key], key
    assert s["matches_log"] is True      # against the TcuResult frames in the CAN log
    assert s["t_serious_s"] is None      # a CAN log has no true plant state


def test_can_log_needs_a_scenario(runs, tmp_path, capsys):
    can_log = tmp_path / "x.log"
    can_log.write_text("(0.000000) vcan0 100##1" + "00" * 24 + "\n")
    rc, out, err = replay_in_process(capsys, str(can_log))
    assert rc == 2 and "--scenario" in err and err.count("\n") == 1


def test_a_replay_keeps_a_control_option_the_logs_scenario_sets_itself():
    """A log recorded before a default changed is replayed with the default of then (NEWER_THAN_SOME_LOGS),
    but only for options its scenario leaves out: an option it names ran as named."""
    from hil.config import load_scenario
    from hil.replay import NEWER_THAN_SOME_LOGS, _named_in

    named = load_scenario(SCENARIOS / "wet_patch.toml", {"control.options.identified.max_kmh": 5.0})
    plain = load_scenario(SCENARIOS / "wet_patch.toml")
    keys = [k for _, _, overrides in NEWER_THAN_SOME_LOGS for k in overrides]
    assert "control.options.identified.max_kmh" in keys and "control.options.identified.cap_kmh" in keys
    assert _named_in(named, "control.options.identified.max_kmh")
    assert not _named_in(plain, "control.options.identified.max_kmh")
    assert not _named_in(named, "control.options.identified.rise_mu")
    assert not _named_in(named, "identifier.options.gp.rail_changes")


def test_a_closed_loop_gp_log_recorded_before_gp_refused_a_window_of_two_rails_replays_the_same(tmp_path):
    """tests/data/draw2-gp-identified-120-9a9465d.mcap: draw 2 of ``hil bench control``'s seed 939869376 (written
    out by ``draw_text``), run by commit 9a9465d with ``hil run DRAW --seed 120 --bus inprocess --set
    control.law=identified --set rail.1.start_s=0.7 --set rail.2.start_s=3.3 --set run.duration_s=1.0``: gp
    confirmed at 0.983 s a peak creep of 0.36-0.40 km/h from samples taken while the rail blended into a patch
    peaking at 0.215 km/h.  Its run metadata has no ``gp_one_rail``, so the replay runs gp with ``one_rail`` off and
    gives what it logged; today's gp, refusing that window, confirms nothing in that second (a new log of the same
    run marks it and replays the same too)."""
    from hil.log.read import read_log

    path = ROOT / "tests" / "data" / "draw2-gp-identified-120-9a9465d.mcap"
    r = hil("replay", path, "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["control"] == "identified" and s["strategy"] == "gp" and s["counterfactual"] is False
    assert s["matches_log"] is True and s["t_identified_s"] == s["logged"]["t_identified_s"] == 0.983
    scenario = tmp_path / "draw2.toml"
    scenario.write_text(read_log(path).metadata["scenario"]["toml"])
    r = hil("run", scenario, "--seed", "120", "--bus", "inprocess", "--set", "control.law=identified", "--set",
            "rail.1.start_s=0.7", "--set", "rail.2.start_s=3.3", "--set", "run.duration_s=1.0", "--out", tmp_path,
            "--json", "--no-rrd")
    assert r.returncode == 0, r.stderr
    today = json.loads(r.stdout)
    assert today["identified"] is False
    r = hil("replay", today["mcap"], "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["matches_log"] is True
