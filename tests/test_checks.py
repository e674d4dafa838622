"""hil.checks over a real 1-second run (in-process lockstep) and ``hil check`` on its log.

The expected figures are computed here with plain loops over what ``hil.read_log`` gives and cantools'
own decoding of the raw frames (not hil.checks' series), so a check that reads the wrong samples,
windows or masks them wrongly, or sums the time in violation wrongly, fails.
"""
import json
import re
import subprocess
import time

import cantools
import pytest

import hil
from hil.checks import CheckFailed, Run, cycle_time, in_range, limit, require, responds, settles
from hil.checks.outcome import TcuFailed, deadlines
from hil.checks.spec import parse_checks
from hil.errors import BenchError, ConfigError

from .conftest import ROOT, SCENARIOS, hil_command, subprocess_env

XSD = ROOT / "tests" / "data" / "junit-10.xsd"


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    out = tmp_path_factory.mktemp("checks")
    scenario = hil.load_scenario(SCENARIOS / "ffcc_a.toml", {"run.duration_s": 1.0})
    summary = hil.run(scenario, bus="inprocess", out_dir=out, progress=False)
    return summary["mcap"]


@pytest.fixture(scope="module")
def raw(log):
    """The log read back plainly: plant states, and the TcuStatus frames decoded by cantools."""
    contents = hil.read_log(log)
    db = cantools.database.load_string(contents.metadata["dbc"]["text"], database_format="dbc")
    status = db.get_message_by_name("TcuStatus")
    frames = [(f.t_s, status.decode(f.data, decode_choices=False)) for f in contents.topic("/can/frames")
              if f.arbitration_id == status.frame_id and f.status == "ok"]
    summary = json.loads(contents.metadata["summary"]["json"])
    return {"state": contents.topic("/plant/state"), "status": frames, "summary": summary}


def test_in_range_over_a_window_finds_first_worst_and_time_in_violation(log, raw):
    t_fault = raw["summary"]["t_fault_s"]
    hi = 1.0
    inside = [(s.t_s, s.creep_speed_kmh) for s in raw["state"] if t_fault <= s.t_s <= t_fault + 0.4]
    over = [(t, v) for t, v in inside if v > hi]
    assert over, "the run no longer slips past 1 km/h within 400 ms of the fault: pick another limit"
    r = in_range("/plant/state.creep_speed_kmh", hi=hi, during=("fault", 0.0, 0.4), req="R-1")(log)
    assert not r.passed and r.req == "R-1" and r.unit == "km/h"
    assert r.first == pytest.approx(over[0])
    assert r.worst == pytest.approx(max(over, key=lambda x: x[1]))
    assert r.samples == len(inside)
    assert r.violation_s == pytest.approx(len(over) * 1e-3)           # 1 ms exchange period per sample
    assert r.margin == pytest.approx(hi - max(v for _, v in over))
    # the line an engineer reads
    assert re.fullmatch(r"\[R-1\] /plant/state\.creep_speed_kmh outside \[-inf, 1\] during fault\+0\.\.400 ms: "
                        r"first \d+\.\d{3} s \(\S+ km/h\), worst \S+ km/h at \d+\.\d{3} s, \d+ ms in violation",
                        r.line()), r.line()
    # the same band before the fault passes, with its margin
    ok = in_range("/plant/state.creep_speed_kmh", hi=hi, during=("start", 0.0, t_fault - 0.001))(log)
    before = [s.creep_speed_kmh for s in raw["state"] if s.t_s <= t_fault - 0.001]
    assert ok.passed and ok.first is None and ok.violation_s == 0
    assert ok.margin == pytest.approx(hi - max(before))


def test_a_dbc_signal_masked_by_its_validity_signal(log, raw):
    """TcuStatus.MuHat where ObserverValid: only valid frames count (the frames decoded by cantools here)."""
    valid = [(t, d["MuHat"]) for t, d in raw["status"] if d["ObserverValid"]]
    lo, hi = 0.155, 0.3
    r = in_range("TcuStatus.MuHat", lo, hi, valid="TcuStatus.ObserverValid")(log)
    bad = [(t, v) for t, v in valid if not lo <= v <= hi]
    assert r.samples == len(valid)
    assert not r.passed and r.first == pytest.approx(bad[0])
    assert r.worst == pytest.approx(min(bad, key=lambda x: min(x[1] - lo, hi - x[1])))


def test_limit_judges_any_summary_key_and_fails_on_missing_or_null(log, raw):
    t_id = raw["summary"]["t_identified_s"]
    assert limit("t_identified_s", hi=t_id + 0.01)(log).passed
    r = limit("t_identified_s", hi=t_id - 0.01, req="ID-1")(log)
    assert not r.passed and r.first == (None, pytest.approx(t_id)) and r.margin == pytest.approx(-0.01)
    assert r.line() == f"[ID-1] t_identified_s = {t_id:.4g} s outside [-inf, {t_id - 0.01:g}] in the run's summary"
    missing = limit("no_such_figure", lo=0.5)(log)
    assert not missing.passed and "not in the run's summary" in missing.reason
    assert limit("identified", lo=1)(log).passed                         # a boolean as 0/1


def test_responds_measures_the_reaction_after_the_fault(log, raw):
    t_fault = raw["summary"]["t_fault_s"]
    first_stage = next(t for t, d in raw["status"] if t >= t_fault and d["Stage"] >= 1)
    reaction_ms = (first_stage - t_fault) * 1e3
    ok = responds("fault", "TcuStatus.Stage >= 1", within_s=(reaction_ms + 1) / 1e3)(log)
    assert ok.passed and ok.margin == pytest.approx(1.0)
    assert ok.note == "lockstep: counted in exchange steps"
    late = responds("fault", "TcuStatus.Stage >= 1", within_s=(reaction_ms - 1) / 1e3)(log)
    assert not late.passed and late.first == pytest.approx((t_fault, reaction_ms))
    never = responds("fault", "TcuStatus.Stage >= 9", within_s=0.05)(log)
    assert not never.passed and "never" in never.line()


def test_cycle_time_counts_steps_in_lockstep_and_says_so(log):
    ok = cycle_time("TcuStatus", nominal_s=1e-3, tolerance_s=2e-4)(log)
    assert ok.passed and ok.samples == 999 and "lockstep: counted in exchange steps of 1 ms" in ok.note
    bad = cycle_time("TcuStatus", nominal_s=2e-3, tolerance_s=2e-4)(log)
    assert not bad.passed and bad.first[1] == pytest.approx(1.0) and bad.violation_s == pytest.approx(0.999)
    silent = cycle_time("TcuResult", nominal_s=5e-3, tolerance_s=1e-4, during=("start", 0.0, 0.4))(log)
    assert not silent.passed and "no cycle" in silent.reason


def test_settles_and_the_events_that_start_windows(log, raw):
    ok = settles("TcuStatus.MuHat", band=(0.14, 0.18), within_s=0.05, hold_s=0.4, valid="TcuStatus.ObserverValid")(log)
    assert ok.passed
    slip = settles("/plant/state.creep_speed_kmh", band=(0.0, 0.5), within_s=0.1, hold_s=0.1, after="fault")(log)
    assert not slip.passed and slip.first[0] > raw["summary"]["t_fault_s"] + 0.1
    for event, key in (("detection", "t_detected_s"), ("identification", "t_identified_s")):
        r = in_range("TcuStatus.Stage", lo=0, during=(event, 0.002, 0.01))(log)
        assert r.window_s == pytest.approx((raw["summary"][key] + 0.002, raw["summary"][key] + 0.01))
        assert r.samples == 9 and r.passed
    with pytest.raises(ConfigError, match="unknown event 'lunch'"):
        in_range("TcuStatus.Stage", lo=0, during="lunch")(log)
    with pytest.raises(ConfigError, match=r"no signal 'MuHta' \(did you mean MuHat"):
        in_range("TcuStatus.MuHta", lo=0)(log)
    with pytest.raises(ConfigError, match="no numeric field 'creep'"):
        in_range("/plant/state.creep", lo=0)(log)


def test_require_lists_every_failed_check_and_prints_the_judging_cost(log):
    t0 = time.perf_counter()
    run = Run.open(log)
    checks = [in_range("TcuStatus.MuHat", 0.0, 0.35, during=("fault", 0.0, 0.2), valid="TcuStatus.ObserverValid"),
              limit("t_identified_s", hi=0.0), responds("fault", "TcuStatus.Stage >= 1", 0.05),
              cycle_time("TcuStatus", 1e-3, 2e-4), settles("/plant/state.creep_speed_kmh", (0, 0.5), 0.1, 0.1, "fault")]
    with pytest.raises(CheckFailed) as e:
        require(run, *checks)
    seconds = time.perf_counter() - t0
    # printed, not asserted: a shared host's load decides it (1.099 s seen under load, ~0.1 s alone);
    # the < 1 s target is the suite benchmark's
    print(f"judging cost: {seconds:.3f} s for opening a 1 s log and 5 checks")
    lines = str(e.value).splitlines()
    assert lines[0] == "2 of 5 checks failed:" and len(lines) == 3
    assert lines[1].startswith("  t_identified_s = ") and "settles not settled in [0, 0.5]" in lines[2]
    assert len(e.value.results) == 5 and isinstance(e.value, AssertionError)


@pytest.mark.parametrize("table, words", [
    ('kind = "in_rnage"\nsignal = "X.Y"', ["[[check]] 1", "kind 'in_rnage'", "in_range"]),
    ('kind = "in_range"\nsignal = "X.Y"\nlo = "low"', ["[[check]] 1", "field 'lo'", "expected a number", "'low'"]),
    ('kind = "in_range"\nlo = 1', ["missing field 'signal'"]),
    ('kind = "limit"\nkey = "r2"\nlo = 1\nwindow = "fault"', ["field 'window' is not one of a limit check's"]),
    ('kind = "in_range"\nsignal = "X.Y"\nlo = 0\nduring = ["fault", "soon"]', ["field 'during'", "a window"]),
    ('kind = "responds"\ntrigger = "fault"\ncondition = "TcuStatus.Stage about 1"\nwithin_s = 0.1',
     ["condition", "SIGNAL OP NUMBER"]),
    ('kind = "in_range"\nsignal = "X.Y"\nlo = 2\nhi = 1', ["lo 2 is above hi 1"]),
])
def test_a_malformed_check_table_is_one_line_naming_file_check_and_field(table, words):
    text = f'[[check]]\nkind = "limit"\nkey = "r2"\nlo = 0.9\n\n[[check]]\nname = "mine"\n{table}\n'
    with pytest.raises(ConfigError) as e:
        parse_checks(text, "suite.toml")
    line = str(e.value)
    assert "\n" not in line and line.startswith("suite.toml: [[check]] 2 (mine): "), line
    for w in words[1:] if words[0] == "[[check]] 1" else words:
        assert w in line, (w, line)


def test_outcome_splits_missed_deadlines_between_the_tcu_and_the_bench():
    base = {"deadlines_exceeded": True, "steps": 1000, "max_missed_fraction": 0.01}
    assert deadlines({"deadlines_exceeded": False}) is None
    tcu = deadlines({**base, "missed_deadlines": 50, "missed_deadlines_plant_started_late": 5})
    assert isinstance(tcu, TcuFailed) and "45 of 1000" in str(tcu)
    bench = deadlines({**base, "missed_deadlines": 50, "missed_deadlines_plant_started_late": 45})
    assert isinstance(bench, BenchError) and bench.exit_code == 5 and "began late" in str(bench)


def _hil_check(*args):
    return subprocess.run(hil_command() + ["check", *map(str, args)], capture_output=True, text=True,
                          env=subprocess_env(), timeout=120)


def test_hil_check_exit_codes_lines_and_junit_valid_against_jenkins_xsd(log, tmp_path):
    from lxml import etree

    schema = etree.XMLSchema(etree.parse(str(XSD)))
    good = SCENARIOS / "suites" / "test_ffcc_a.toml"
    r = _hil_check(log, good, "--junitxml", tmp_path / "good.xml")
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.count("PASS ") == 5 and "5 of 5 checks passed" in r.stdout
    assert schema.validate(etree.parse(str(tmp_path / "good.xml"))), schema.error_log

    bad = tmp_path / "bad.toml"
    bad.write_text(good.read_text() + '\n[[check]]\nkind = "in_range"\nsignal = "/plant/state.creep_speed_kmh"\n'
                   'hi = 1.0\nduring = "fault"\nreq = "ADH-1"\n')
    r = _hil_check(log, bad, "--junitxml", tmp_path / "bad.xml")
    assert r.returncode == 1, r.stdout + r.stderr
    fails = [ln for ln in r.stdout.splitlines() if ln.startswith("FAIL ")]
    assert len(fails) == 1 and fails[0].startswith("FAIL [ADH-1] /plant/state.creep_speed_kmh outside [-inf, 1]")
    xml = etree.parse(str(tmp_path / "bad.xml"))
    assert schema.validate(xml), schema.error_log
    suite = xml.getroot()[0]
    assert suite.get("failures") == "1" and suite.get("errors") == "0" and suite.get("tests") == "6"
    props = {p.get("name"): p.get("value") for p in suite.iter("property")}
    assert re.fullmatch(r"[0-9a-f]{64}", props["dbc_sha256"]) and props["railway_hil_version"]
    out = [c.findtext("system-out") for c in suite.iter("testcase") if c.find("failure") is not None][0]
    png = re.search(r"\[\[ATTACHMENT\|(.+\.png)\]\]", out).group(1)
    assert open(png, "rb").read(8) == b"\x89PNG\r\n\x1a\n"

    malformed = tmp_path / "malformed.toml"
    malformed.write_text('[[check]]\nkind = "limit"\nkey = "r2"\nlo = "high"\n')
    r = _hil_check(log, malformed)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith(f"hil check: error: {malformed}: [[check]] 1: field 'lo'"), r.stderr
    r = _hil_check(malformed, good)
    assert r.returncode == 2 and "not an MCAP file" in r.stderr and "Traceback" not in r.stderr
    cut = tmp_path / "cut.mcap"
    data = open(log, "rb").read()
    cut.write_bytes(data[:len(data) // 2])                 # a log cut mid-write: not judged
    r = _hil_check(cut, good)
    assert r.returncode == 2 and "cannot judge a damaged log" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_timing_checks_use_receive_wall_times_in_a_real_time_run(tmp_path):
    """In real time cycle_time measures the receive wall times (the frames' wall_time_ns here), not steps."""
    scenario = hil.load_scenario(SCENARIOS / "ffcc_a.toml", {"run.duration_s": 0.3, "run.fault_time_s": 0.2})
    summary = hil.run(scenario, bus="inprocess", mode="realtime", out_dir=tmp_path, progress=False)
    contents = hil.read_log(summary["mcap"])
    status_id = 0x120
    wall = sorted(f.wall_time_ns for f in contents.topic("/can/frames")
                  if f.arbitration_id == status_id and f.status == "ok")
    gaps_ms = [(b - a) * 1e-6 for a, b in zip(wall, wall[1:])]
    loose = cycle_time("TcuStatus", nominal_s=1e-3, tolerance_s=1.0)(summary["mcap"])
    assert loose.passed and loose.note == "receive wall time" and loose.samples == len(gaps_ms)
    assert loose.margin == pytest.approx((1.0 - max(abs(g - 1.0) for g in gaps_ms) * 1e-3) * 1e3)
    strict = cycle_time("TcuStatus", nominal_s=1e-3, tolerance_s=0.0)(summary["mcap"])
    off = [g for g in gaps_ms if abs(g - 1.0) > 1e-6]
    assert not strict.passed and strict.first[1] == pytest.approx(off[0])
    assert strict.worst[1] == pytest.approx(max(gaps_ms, key=lambda g: abs(g - 1.0)))
    # a share of the intervals may lie outside: with a tolerance at the median error about half do here; a share
    # that covers all of them passes, one interval fewer fails, and the margin is that of the worst one kept
    errors = sorted(abs(g - 1.0) for g in gaps_ms)
    tol_ms = errors[len(errors) // 2]
    outside = sum(e > tol_ms + 1e-6 for e in errors)
    assert 0 < outside < len(gaps_ms)
    covered = cycle_time("TcuStatus", 1e-3, tol_ms * 1e-3, max_outside_fraction=(outside + 0.5) / len(gaps_ms))(
        summary["mcap"])
    assert covered.passed and f"{outside} of {len(gaps_ms)} intervals outside, at most {outside}" in covered.line()
    assert covered.margin == pytest.approx(tol_ms - errors[len(errors) - 1 - outside], abs=1e-6)
    short = cycle_time("TcuStatus", 1e-3, tol_ms * 1e-3, max_outside_fraction=(outside - 0.5) / len(gaps_ms))(
        summary["mcap"])
    assert not short.passed and short.margin < 0


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_hil_check_judges_a_rigs_can_log_with_its_dbc(log, raw, tmp_path, suffix):
    """A rig's CAN log (written here by python-can from the run's frames, as a rig's logger would) judged by
    the same checks with --dbc: signals decoded by their DBC names, timing from the frames' timestamps; a
    summary figure has nothing to judge in a CAN log and fails saying so; a DBC that is not one is one line."""
    import can

    contents = hil.read_log(log)
    dbc = tmp_path / "hil.dbc"
    dbc.write_text(contents.metadata["dbc"]["text"])
    path = tmp_path / f"rig{suffix}"
    t0 = 1_700_000_000.0
    with can.Logger(str(path)) as logger:
        for f in contents.topic("/can/frames"):
            if f.direction == "rx" and f.status == "ok":
                logger(can.Message(timestamp=t0 + f.t_s, arbitration_id=f.arbitration_id, data=f.data,
                                   is_extended_id=False, is_fd=f.is_fd, bitrate_switch=f.bitrate_switch))
    checks = tmp_path / "rig.toml"
    checks.write_text('[[check]]\nname = "mu"\nreq = "OBS-1"\nkind = "in_range"\nsignal = "TcuStatus.MuHat"\n'
                      'lo = -0.01\nhi = 0.35\n\n'
                      '[[check]]\nname = "no figure"\nreq = "SUM-1"\nkind = "limit"\nkey = "t_identified_s"\nhi = 1.0\n')
    r = subprocess.run(hil_command() + ["check", str(path), str(checks), "--dbc", str(dbc)], capture_output=True,
                       text=True, env=subprocess_env(), cwd=ROOT, timeout=120)
    assert r.returncode == 1, r.stderr
    lines = r.stdout.splitlines()
    mu_hat = [v["MuHat"] for _, v in raw["status"]]
    assert "PASS [OBS-1]" in lines[0] and len(mu_hat) > 900 and -0.01 <= min(mu_hat) and max(mu_hat) <= 0.35
    assert lines[1].startswith("FAIL [SUM-1]") and "summary" in lines[1]
    bad = tmp_path / "bad.dbc"
    bad.write_text("not a dbc at all {")
    r = subprocess.run(hil_command() + ["check", str(path), str(checks), "--dbc", str(bad)], capture_output=True,
                       text=True, env=subprocess_env(), cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "--dbc" in r.stderr


def test_torque_sign_judges_the_tcus_torque_against_the_drivers_demand(log, raw):
    """Every TorqueCommand of the run has the demand's sign (both positive: traction); a negative tolerance is
    one ConfigError line."""
    from hil.checks import torque_sign

    contents = hil.read_log(log)
    db = cantools.database.load_string(contents.metadata["dbc"]["text"], database_format="dbc")
    cmd = db.get_message_by_name("TorqueCommand")
    torques = [cmd.decode(f.data)["TorqueCmd"] for f in contents.topic("/can/frames")
               if f.arbitration_id == cmd.frame_id and f.status == "ok"]
    assert torques and min(torques) > 0
    r = torque_sign("TorqueCommand.TorqueCmd", "DriverDemand.DemandTorque")(log)
    assert r.passed and r.kind == "torque_sign" and r.samples == len(torques)
    assert r.margin == pytest.approx(min(torques))
    with pytest.raises(ConfigError, match="tolerance"):
        torque_sign("TorqueCommand.TorqueCmd", "DriverDemand.DemandTorque", tolerance=-1.0)
