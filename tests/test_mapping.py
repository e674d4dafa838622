"""A TCU's own DBC (``[bus] dbc`` and ``[bus.mapping]``, hil/bus/mapping.py): each mapping problem as one
line naming the file and the key; the mapped codec's quantisation and saturation; the built-in TCU end
to end over ``scenarios/suites/their.dbc`` (classical CAN, scaled integers); and the example suite
``scenarios/suites/test_their_tcu.toml`` in real pytest sessions, in lockstep and (marked realtime, where
SCHED_FIFO is granted) in real time, where the built-in TCU passes every check and each faulty example TCU
fails exactly its own; and the JUnit file's properties naming the DBCs the runs spoke."""
import importlib
import json
import os
import sys
import tempfile
import xml.etree.ElementTree as ET

import pytest

from hil.config import load_scenario
from hil.errors import ConfigError

from .conftest import ROOT, SCENARIOS

pytest_plugins = ["pytester"]

THEIR = {"bus.dbc": "suites/their.dbc", "bus.mapping.motor_speed_rad_s": "Sensors.MotorSpeed",
         "bus.mapping.train_speed_ms": "Sensors.TrainSpeed", "bus.mapping.demand_torque_nm": "Notch.DemandTorque",
         "bus.mapping.torque_command_nm": "TcuCmd.TorqueRequest"}
SUITE = SCENARIOS / "suites" / "test_their_tcu.toml"
#: their DBC with a TcuState (0x201) and a TcuDiag (0x202) beside the command, and a TcuVersion (0x310)
STATUS_DBC = {**THEIR, "bus.dbc": "../tests/data/their_with_status.dbc"}
FAULTY = SCENARIOS / "suites" / "faulty_tcus"
CHECKS = {"answers within three periods", "commands every period", "no macro-slip", "uses the wet patch's adhesion"}


@pytest.mark.parametrize("change, key, words", [
    ({"bus.mapping.train_speed_ms": "Speeds.TrainSpeed"}, "[bus.mapping] train_speed_ms", "no message 'Speeds'"),
    ({"bus.mapping.train_speed_ms": "Sensors.Speed"}, "[bus.mapping] train_speed_ms", "has no signal 'Speed'"),
    ({"bus.mapping.train_speed_ms": "Notch.NotchPosition"}, "[bus.mapping] train_speed_ms", "too narrow"),
    ({"bus.mapping.torque_command_nm": "Notch.DemandTorque"}, "[bus.mapping] torque_command_nm", "of its own"),
    ({"bus.mapping.creep_kmh": "Sensors.MotorSpeed"}, "[bus.mapping] creep_kmh", "unknown quantity"),
    ({"bus.mapping.train_speed_ms": 3}, "[bus.mapping] train_speed_ms", "Message.Signal"),
    ({"bus.dbc": "suites/nowhere.dbc"}, "[bus] dbc", "no such file"),
    ({"bus.auth": "on"}, "[bus] auth", "unauthenticated"),
    ({**STATUS_DBC, "bus.mapping.tcu_frames": ["TcuStatus"]}, "[bus.mapping] tcu_frames", "no message 'TcuStatus'"),
    ({**STATUS_DBC, "bus.mapping.tcu_frames": ["TcuCmd"]}, "[bus.mapping] tcu_frames", "carries torque_command_nm"),
    ({**STATUS_DBC, "bus.mapping.tcu_frames": "TcuState"}, "[bus.mapping] tcu_frames", "must be a list"),
    ({"run.exchange_period_s": 2e-3}, "[bus.mapping] ", "cycle time of 1 ms (GenMsgCycleTime); the scenario's "
     "exchange period is 2 ms: set run.exchange_period_s = 0.001"),
])
def test_each_mapping_problem_is_one_line_naming_the_file_and_the_key(change, key, words):
    with pytest.raises(ConfigError) as e:
        load_scenario(SCENARIOS / "ffcc_a.toml", {**THEIR, **change})
    text = str(e.value)
    assert "\n" not in text and text.startswith(f"{SCENARIOS / 'ffcc_a.toml'}: {key}") and words in text, text


def test_a_mapping_without_its_dbc_and_a_missing_quantity_are_refused():
    without = {k: v for k, v in THEIR.items() if k != "bus.dbc"}
    with pytest.raises(ConfigError, match=r"\[bus.mapping\]: needs \[bus\] dbc"):
        load_scenario(SCENARIOS / "ffcc_a.toml", without)
    partial = {k: v for k, v in THEIR.items() if k != "bus.mapping.demand_torque_nm"}
    with pytest.raises(ConfigError, match=r"\[bus.mapping\] demand_torque_nm: missing"):
        load_scenario(SCENARIOS / "ffcc_a.toml", partial)


def test_a_dbcs_bit_rates_are_read_from_its_attributes():
    """``Baudrate`` (their.dbc: 500 kbit/s) and a CAN FD data rate (``BaudrateCANFD``, as CANdb++ writes it);
    None where the DBC names none."""
    import cantools

    from hil.bus.mapping import dbc_bitrates

    text = (SCENARIOS / "suites" / "their.dbc").read_text()
    assert dbc_bitrates(cantools.database.load_string(text, database_format="dbc")) == (500_000, None)
    fd = text.replace('BA_DEF_ "Baudrate" INT 1 1000000;', 'BA_DEF_ "Baudrate" INT 1 1000000;\n'
                      'BA_DEF_ "BaudrateCANFD" INT 1 16000000;').replace('BA_ "Baudrate" 500000;',
                                                                     'BA_ "Baudrate" 500000;\nBA_ "BaudrateCANFD" 2000000;')
    assert dbc_bitrates(cantools.database.load_string(fd, database_format="dbc")) == (500_000, 2_000_000)
    bare = "\n".join(ln for ln in text.splitlines() if "Baudrate" not in ln)
    assert dbc_bitrates(cantools.database.load_string(bare, database_format="dbc")) == (None, None)


def test_the_mapped_codec_quantises_to_their_scale_and_saturates():
    """Values come back within half their signal's scale; a speed beyond the signal's range is sent as
    its end; the frames are classical CAN of 8 bytes, the trigger (the motor speed's message) last; a
    received value outside their DBC's range, or a frame of another length, is rejected by reason."""
    from identifier.messages import DriverDemand, SensorReading, TorqueCommand
    from hil.bus.mapping import codec_for

    sc = load_scenario(SCENARIOS / "ffcc_a.toml", THEIR)
    plant, tcu = codec_for(sc), codec_for(sc)
    frames = plant.sensor_frames(DriverDemand(0, 5432.1), SensorReading(0, 63.7491, 10.0013))
    assert [f.arbitration_id for f in frames] == [0x180, 0x181]
    assert all(not f.is_fd and len(f.data) == 8 for f in frames)
    got = [tcu.classify(f) for f in frames]
    assert [g[0].name for g in got] == ["DriverDemand", "PlantSensor"]
    demand, reading = got[0][0].value, got[1][0].value
    assert abs(demand.torque_nm - 5432.1) <= 0.25 and abs(reading.motor_speed_rad_s - 63.7491) <= 0.01
    assert abs(reading.train_speed_ms - 10.0013) <= 0.001 and reading.step == 0
    fast = tcu.classify(plant.sensor_frames(DriverDemand(1, 0.0), SensorReading(1, 5000.0, 10.0))[1])[0].value
    assert fast.motor_speed_rad_s == 1300.0 and fast.step == 1
    cmd, status = plant.classify(tcu.command(TorqueCommand(1, 4000.26)))
    assert status == "ok" and abs(cmd.value.torque_nm - 4000.26) <= 0.25
    import can

    beyond = can.Message(arbitration_id=0x200, data=b"\xff\xff" + bytes(6), is_extended_id=False)   # 32767.5 N.m
    assert plant.classify(beyond) == (None, "out_of_range:TorqueRequest")       # their DBC says at most 32000
    assert plant.classify(can.Message(arbitration_id=0x200, data=bytes(7), is_extended_id=False)) == (None, "bad_length")


def _summary(args, tmp_path, name):
    from hil.testing import run_hil

    sets = [a for k, v in THEIR.items() for a in ("--set", f'{k}="{v}"')]
    r = run_hil("run", str(SCENARIOS / "ffcc_a.toml"), "--set", "run.duration_s=1.0", *sets, "--json", "--no-rrd",
                "--out", str(tmp_path / name), *args)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def _external(tmp_path):
    """``hil tcu`` with the same ``--set`` items on a local bus, and ``hil run --tcu external`` on it: the run's
    summary and the TCU's report."""
    import subprocess

    from hil.testing import hil_command, subprocess_env

    sets = [a for k, v in THEIR.items() for a in ("--set", f'{k}="{v}"')]
    bus = tempfile.mkdtemp(prefix="hil-bus-test-")
    tcu = subprocess.Popen(hil_command() + ["tcu", str(SCENARIOS / "ffcc_a.toml"), "--bus", f"localbus:{bus}",
                                            "--set", "run.duration_s=1.0", *sets, "--json"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env(), cwd=ROOT)
    try:
        summary = _summary(["--bus", f"localbus:{bus}", "--tcu", "external"], tmp_path, "ext")
        out, err = tcu.communicate(timeout=120)
    finally:
        if tcu.poll() is None:
            tcu.kill()
            tcu.wait()
        os.rmdir(bus)
    assert tcu.returncode == 0, err
    return summary, json.loads(out)


def test_the_built_in_tcu_identifies_over_their_classical_can_dbc(tmp_path):
    """ffcc_a, 1 s, lockstep, the built-in TCU over their.dbc, in this process, as a TCU process and as
    ``hil tcu`` on the bus (external): the same figures (the readings count from the plant's 'running'
    heartbeat, so the steps agree; the built-in TCU answers no probe: 1000 readings); the fault is
    detected and identified as on the native DBC (bounds from the paper's own error scale), the log
    keeps their DBC, the checks decode its signals and ``hil replay`` repeats the identification."""
    from hil.checks import Run

    inproc = _summary(["--bus", "inprocess"], tmp_path, "a")
    proc = _summary([], tmp_path, "b")
    external, report = _external(tmp_path)
    for key in ("t_detected_s", "t_identified_s", "peak_mu", "peak_creep_kmh", "macro_slip_s", "samples"):
        assert inproc[key] == proc[key] == external[key], key
    assert external["transport"] == "external" and external["rejected_frames"] == {}
    assert report["rejected_frames"] == {} and report["sensor_frames"] == 1000
    assert proc["frame_auth"] == "off" and proc["rejected_frames"] == {} and proc["tcu_rejected_frames"] == {}
    assert 0.5 <= proc["t_detected_s"] <= 0.55 and proc["t_identified_s"] <= 0.7
    # their DBC's Baudrate (500 kbit/s) sets the load: three 8-byte classical frames a 1 ms period, each at worst
    # 44 + 64 bits and (34 + 64 - 1) // 4 = 24 stuff bits: 396 bits of the 500 a millisecond carries
    assert proc["bus_bitrate"] == 500_000 and abs(proc["mapped_bus_load_percent"] - 79.2) < 1e-9, proc
    assert proc["peak_mu_err_percent"] < 2.0 and proc["peak_creep_err_percent"] < 5.0
    run = Run.open(proc["mcap"])
    assert run.log.metadata["dbc"]["name"] == "their.dbc"
    torque = run.signal("TcuCmd.TorqueRequest")
    assert len(torque.values) == 1000 and torque.unit == "N.m"
    from hil.replay import replay_log

    again = replay_log(proc["mcap"])          # the frames on their DBC, decoded as the TCU did: the same events
    assert again["source"] == "mcap-frames" and again["matches_log"] is True and again["sensor_readings"] == 1000


@pytest.fixture(scope="module")
def _loaded():
    """What the sessions import, imported here first: pytester's in-process sessions remove the modules
    they imported when they end, and numpy cannot be imported twice in one process."""
    for name in ("matplotlib.pyplot", "hil.checks.offline", "hil.exchange", "hil.view", "hil.config", "identifier"):
        importlib.import_module(name)


def _suite(pytester, tmp, tcu_args):
    out = pytester.path / "junit.xml"
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", f"localbus:{tmp}",
                                "--hil-out", str(pytester.path / "hil-out"), "--junitxml", str(out), *tcu_args,
                                str(SUITE))
    root = ET.parse(str(out)).getroot()
    cases = {c.get("name").split("-", 1)[1]: {x.tag for x in c} for c in root.iter("testcase")}   # "N-name"
    failed = {n for n, tags in cases.items() if "failure" in tags}
    errors = [n for n, tags in cases.items() if "error" in tags or "skipped" in tags]
    passed = {n for n, tags in cases.items() if not tags & {"failure", "error", "skipped"}}
    return result, failed, errors, passed


@pytest.mark.parametrize("tcu, fails", [
    (None, set()),
    ("keeps_demand.py --bus {bus}", {"no macro-slip", "uses the wet patch's adhesion"}),
    ("answers_late.py {scenario} --bus {bus}", {"answers within three periods"}),
])
def test_each_faulty_tcu_fails_exactly_its_checks_and_the_built_in_one_passes(pytester, _loaded, tcu, fails):
    """The example suite on wet_patch (3 s, lockstep) over their.dbc on a local bus: the built-in TCU passes all
    four checks; the TCU that keeps the demand through the slip fails the two adhesion checks and no other;
    the one that answers five periods late fails the round-trip check and no other.  The JUnit file says so."""
    os.environ.setdefault("PYTHONPATH", str(ROOT))
    with tempfile.TemporaryDirectory(prefix="hil-bus-test-") as tmp:
        args = [] if tcu is None else ["--hil-tcu", "external", "--hil-tcu-cmd", f"{sys.executable} {FAULTY}/{tcu}"]
        result, failed, errors, passed = _suite(pytester, tmp, args)
    assert not errors, result.stdout.str()
    assert failed == fails, result.stdout.str()
    assert passed == CHECKS - fails, result.stdout.str()


def test_a_frozen_tcus_log_gets_the_same_verdict_per_check_from_pytest_and_hil_check(pytester, _loaded):
    """Issue 49 item 8, one judge: a TCU on their.dbc that freezes after 300 readings (tests/data/freezes_tcu.py)
    under the example suite (lockstep on a local bus, 1 s of silence allowed: the run ends 0.3 s in).  pytest fails every check
    (the TCU fell silent); ``hil check`` on the log it left fails every check too, each saying why, and exits 1
    -- where it once passed the cycle time judged on the frames up to the freeze.  That check alone, judged
    without the run's verdict, fails too: its frame stops long before the record does."""
    import subprocess

    from hil.checks import Run, cycle_time
    from hil.testing import hil_command, subprocess_env

    suite = pytester.path / "test_frozen.toml"
    suite.write_text(SUITE.read_text().replace('scenario = "../wet_patch.toml"', f'scenario = "{SCENARIOS / "wet_patch.toml"}"')
                     .replace('"bus.lockstep_silence_s" = 5.0', '"bus.lockstep_silence_s" = 1.0'))
    os.environ.setdefault("PYTHONPATH", str(ROOT))
    with tempfile.TemporaryDirectory(prefix="hil-bus-test-") as tmp:
        out = pytester.path / "junit.xml"
        result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", f"localbus:{tmp}",
                                    "--hil-out", str(pytester.path / "hil-out"), "--junitxml", str(out),
                                    "--hil-tcu", "external", "--hil-tcu-cmd",
                                    f"{sys.executable} {ROOT / 'tests' / 'data' / 'freezes_tcu.py'} --bus {{bus}} --after 300",
                                    str(suite))
    root = ET.parse(str(out)).getroot()
    by_pytest = {c.get("name").split("-", 1)[1]: ("failure" if c.find("failure") is not None else
                                                  "error" if c.find("error") is not None else "pass")
                 for c in root.iter("testcase")}
    assert by_pytest == {name: "failure" for name in CHECKS}, result.stdout.str()
    messages = [c.find("failure").get("message") for c in root.iter("testcase")]
    assert all(m.startswith("the TCU fell silent or died") for m in messages), messages
    log = next((pytester.path / "hil-out").rglob("*.mcap"))
    r = subprocess.run(hil_command() + ["check", str(log), str(suite), "--junitxml", str(pytester.path / "check.xml")],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    by_check = {c.get("name"): ("failure" if c.find("failure") is not None else
                                "error" if c.find("error") is not None else "pass")
                for c in ET.parse(str(pytester.path / "check.xml")).getroot().iter("testcase")}
    assert by_check == by_pytest, r.stdout
    from lxml import etree

    schema = etree.XMLSchema(etree.parse(str(ROOT / "tests" / "data" / "junit-10.xsd")))
    for xml in (out, pytester.path / "check.xml"):              # both still Jenkins' JUnit
        assert schema.validate(etree.parse(str(xml))), schema.error_log
    assert "0 of 4 checks passed" in r.stdout and r.stdout.count("the TCU fell silent or died") >= 5, r.stdout
    alone = cycle_time("TcuCmd", 0.001, 0.0005, max_outside_fraction=0.02)(Run.open(log))
    assert not alone.passed and "no TcuCmd in the last" in alone.note and alone.violation_s > 2.5, alone.line()
    print(alone.line())


def test_two_tcu_frames_with_their_own_ids_are_logged_range_checked_and_checkable(tmp_path):
    """Issue 49 item 7: a TCU (tests/data/status_tcu.py, python-can and cantools) that sends, besides its
    command TcuCmd (0x200), TcuState (0x201) and TcuDiag (0x202), both named by ``tcu_frames``, and frames of
    ids the mapping does not name (TcuVersion 0x310 of its DBC, 0x7FF of none).  ffcc_a, 1 s, lockstep on a
    local bus.  What the TCU says it sent is the oracle: the summary counts the unmapped ids frame for frame
    and the hot TcuState frames (200 degC, past the DBC's 150) under ``out_of_range_signals`` (every signal
    of a frame received listed, 0 included); the run still runs (an unmapped signal out of range rejects no
    frame); the log keeps both frames, whose signals the checks decode; the text summary lists the ids."""
    import signal as sig
    import subprocess

    from hil.checks import Run, cycle_time, in_range, limit
    from hil.commands.run import print_summary
    from hil.testing import run_hil, subprocess_env

    sets = [a for k, v in STATUS_DBC.items() for a in ("--set", f'{k}="{v}"')]
    sets += ["--set", 'bus.mapping.tcu_frames=["TcuState", "TcuDiag"]']
    report = tmp_path / "sent.json"
    with tempfile.TemporaryDirectory(prefix="hil-bus-test-") as bus:
        tcu = subprocess.Popen([sys.executable, str(ROOT / "tests" / "data" / "status_tcu.py"), "--bus",
                                f"localbus:{bus}", "--report", str(report), "--hot", "100:110"],
                               env=subprocess_env(), stderr=subprocess.PIPE, text=True)
        try:
            r = run_hil("run", str(SCENARIOS / "ffcc_a.toml"), "--set", "run.duration_s=1.0", *sets, "--json",
                        "--no-rrd", "--out", str(tmp_path / "out"), "--bus", f"localbus:{bus}", "--tcu", "external")
        finally:
            tcu.send_signal(sig.SIGTERM)
            _, err = tcu.communicate(timeout=30)
    assert r.returncode == 0, r.stderr[-3000:]
    sent = json.loads(report.read_text())
    s = json.loads(r.stdout)
    assert sent["TcuVersion"] >= 10 and sent["TcuState_hot"] == 10, sent
    assert s["unmapped_ids"] == {"0x310": sent["TcuVersion"], "0x7FF": sent["0x7FF"]}, s["unmapped_ids"]
    assert s["rejected_frames"] == {}, s["rejected_frames"]
    oor = s["out_of_range_signals"]
    assert oor["TcuState.Temperature"] == sent["TcuState_hot"] == 10, oor
    assert {k for k, n in oor.items() if n} == {"TcuState.Temperature"}, oor
    assert {"TcuCmd.TorqueRequest", "TcuCmd.MuEstimate", "TcuState.SlipStage", "TcuDiag.Counter"} <= set(oor), oor

    run = Run.open(s["mcap"])
    temperature = run.signal("TcuState.Temperature")
    assert temperature.unit == "degC" and int((temperature.values > 150).sum()) == 10
    assert len(temperature.values) == sent["TcuState"]              # every TcuState frame logged and decoded
    assert len(run.signal("TcuDiag.Counter").values) == sent["TcuDiag"]
    build = run.signal("TcuVersion.Build")             # unmapped, but in the log's DBC: logged, decoded, checkable
    assert len(build.values) == sent["TcuVersion"] and set(build.values) == {49.0}
    assert not in_range("TcuState.Temperature", hi=150.0)(run).passed
    assert not limit("out_of_range_signals.TcuState.Temperature", hi=0)(run).passed
    assert limit("out_of_range_signals.TcuCmd.TorqueRequest", hi=0)(run).passed
    assert limit("unmapped_ids.0x7FF", lo=1)(run).passed
    assert cycle_time("TcuState", 0.001, 0.0005, during=("start", 0.0, 1.0))(run).passed
    import io

    text = io.StringIO()
    print_summary(s, file=text)
    assert f"frames of ids the mapping does not name (not acted on): 0x310 x{sent['TcuVersion']}, 0x7FF x" in \
        text.getvalue(), text.getvalue()
    assert "signals outside their DBC range: TcuState.Temperature x10" in text.getvalue()


def test_an_external_tcus_printed_reproduce_and_re_judge_commands_give_its_verdicts_again(pytester, _loaded):
    """Issue 49 item 4 with a TCU of another make: the example suite (lockstep, local bus) on keeps_demand.py,
    which fails ADH-1 and ADH-2.  The ``reproduce:`` line of a failed check carries the TCU command; run as
    printed (a new pytest process, the same bus) it fails that check again with the same FAIL line; the
    ``re-judge:`` line (``hil check`` on the log by the suite's file) gives each of the four checks the
    verdict pytest gave it."""
    import shlex
    import subprocess

    from hil.testing import hil_command, subprocess_env

    os.environ.setdefault("PYTHONPATH", str(ROOT))
    with tempfile.TemporaryDirectory(prefix="hil-bus-test-") as tmp:
        result, failed, errors, passed = _suite(pytester, tmp, ["--hil-tcu", "external", "--hil-tcu-cmd",
                                                                f"{sys.executable} {FAULTY}/keeps_demand.py --bus {{bus}}"])
        assert failed == {"no macro-slip", "uses the wet patch's adhesion"} and not errors, result.stdout.str()
        root = ET.parse(str(pytester.path / "junit.xml")).getroot()
        case = next(c for c in root.iter("testcase") if c.get("name").endswith("-no macro-slip"))
        text = case.findtext("system-out")
        fail = [ln for ln in text.splitlines() if ln.startswith("FAIL ")]
        assert len(fail) == 1 and fail[0].startswith("FAIL [ADH-1] no macro-slip (macro_slip_s) = "), text
        line = next(ln for ln in text.splitlines() if ln.startswith("reproduce: "))
        argv = shlex.split(line.split(": ", 1)[1])
        assert argv[0] == "pytest" and argv[1] == f"{SUITE}::3-no macro-slip", argv
        assert argv[argv.index("--hil-tcu-cmd") + 1] == f"{sys.executable} {FAULTY}/keeps_demand.py --bus {{bus}}"
        assert argv[argv.index("--hil-bus") + 1] == f"localbus:{tmp}" and "--strategy" not in line
        again = subprocess.run([sys.executable, "-m", "pytest", *argv[1:], "--hil-out", str(pytester.path / "again")],
                               capture_output=True, text=True, env=subprocess_env(), timeout=300, cwd="/")
    assert again.returncode == 1 and "1 failed" in again.stdout, again.stdout[-3000:] + again.stderr[-2000:]
    assert [ln.strip() for ln in again.stdout.splitlines() if ln.strip().startswith("FAIL ")] == fail, again.stdout
    rejudge = shlex.split(next(ln for ln in text.splitlines() if ln.startswith("re-judge: ")).split(": ", 1)[1])
    assert rejudge[:2] == ["hil", "check"] and rejudge[3] == str(SUITE), rejudge
    r = subprocess.run(hil_command() + rejudge[1:], capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    by_check = {ln.split("] ", 1)[1].split(" (")[0]: ln[:4] for ln in r.stdout.splitlines()
                if ln.startswith(("PASS [", "FAIL ["))}
    assert by_check == {**{n: "PASS" for n in passed}, **{n: "FAIL" for n in failed}}, r.stdout


def test_hil_run_says_a_mapping_problem_in_one_line_with_exit_2(tmp_path):
    from hil.testing import run_hil

    sets = [a for k, v in {**THEIR, "bus.mapping.motor_speed_rad_s": "Sensors.Motor"}.items()
            for a in ("--set", f'{k}="{v}"')]
    r = run_hil("run", str(SCENARIOS / "ffcc_a.toml"), "--bus", "inprocess", *sets, "--out", str(tmp_path))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "[bus.mapping] motor_speed_rad_s: message Sensors of their.dbc has no signal 'Motor'" in r.stderr


def test_the_junit_file_names_each_dbc_the_runs_spoke_with_its_digest(pytester, _loaded):
    """A session of two runs, one over their.dbc (a mapped scenario) and one over the HIL's own DBC: the suite's
    properties hold a ``dbc`` / ``dbc_sha256`` pair for each, in the order the runs used them, the digest that
    of the file itself (computed here from its bytes)."""
    import hashlib

    sets = "".join(f'"{k}" = "{v}"\n' for k, v in THEIR.items())
    check = '[[check]]\nname = "ran"\nkind = "limit"\nkey = "sim_s"\nlo = 0.1\n'
    pytester.makefile(".toml", test_a_ours=f'scenario = "{SCENARIOS / "ffcc_a.toml"}"\n[set]\n"run.duration_s" = 0.3\n"run.fault_time_s" = 0.2\n'
                      + check,
                      test_b_theirs=f'scenario = "{SCENARIOS / "ffcc_a.toml"}"\n[set]\n"run.duration_s" = 0.3\n"run.fault_time_s" = 0.2\n{sets}'
                      + check)
    out = pytester.path / "junit.xml"
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", "inprocess",
                                "--hil-out", str(pytester.path / "hil-out"), "--junitxml", str(out))
    result.assert_outcomes(passed=2)
    from lxml import etree

    schema = etree.XMLSchema(etree.parse(str(ROOT / "tests" / "data" / "junit-10.xsd")))
    assert schema.validate(etree.parse(str(out))), schema.error_log
    props = [(p.get("name"), p.get("value")) for p in ET.parse(str(out)).getroot().iter("property")]
    dbcs = [(name, digest) for (k1, name), (k2, digest) in zip(props, props[1:]) if (k1, k2) == ("dbc", "dbc_sha256")]
    sha = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in (ROOT / "hil" / "hil.dbc", SCENARIOS / "suites" / "their.dbc")}
    assert dbcs == [("hil.dbc", sha[ROOT / "hil" / "hil.dbc"]), ("their.dbc", sha[SCENARIOS / "suites" / "their.dbc"])], props
    assert sum(k == "dbc_sha256" for k, _ in props) == 2, props


def _sched_fifo_or_skip():
    """SCHED_FIFO is granted here (tried on this process, its policy given back) and ``chrt`` is there to give
    it to the TCU under test; otherwise a skip saying why, and under CI=true (root) a failure."""
    import shutil

    old = (os.sched_getscheduler(0), os.sched_getparam(0))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except PermissionError as e:
        why = f"SCHED_FIFO is not granted here ({e}; needs root or CAP_SYS_NICE)"
    else:
        os.sched_setscheduler(0, *old)
        why = None if shutil.which("chrt") else "chrt (util-linux) is not installed"
    if why:
        assert os.environ.get("CI") != "true", f"CI=true: the real-time suite must run (root expected), but {why}"
        pytest.skip(why)


def _suite_in_real_time(tmp_path, tcu):
    """The example suite in real time on a fresh local bus, ``tcu`` (None: the built-in one) under
    SCHED_FIFO: (the pytest process, {check name: its JUnit failure message} of the checks that failed,
    {check name: its JUnit error message} of those that errored), the JUnit checked against its schema, one
    case per check, none skipped, and the bus and DBC in its properties."""
    import subprocess

    from lxml import etree

    from hil.testing import subprocess_env

    tmp_path.mkdir(parents=True)
    junit = tmp_path / "junit.xml"
    with tempfile.TemporaryDirectory(prefix="hil-bus-test-") as bus:
        args = [] if tcu is None else ["--hil-tcu", "external", "--hil-tcu-cmd",
                                       f"chrt -f 10 {sys.executable} {FAULTY}/{tcu}"]
        r = subprocess.run([sys.executable, "-m", "pytest", "-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "-q",
                            str(SUITE), "--hil-bus", f"localbus:{bus}", "--hil-mode", "realtime",
                            "--hil-out", str(tmp_path / "out"), "--junitxml", str(junit), *args],
                           cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=300)
    out = r.stdout[-3000:] + r.stderr[-2000:]
    schema = etree.XMLSchema(etree.parse(str(ROOT / "tests" / "data" / "junit-10.xsd")))
    assert schema.validate(etree.parse(str(junit))), schema.error_log
    root = ET.parse(str(junit)).getroot()
    cases = {c.get("name").split("-", 1)[1]: c for c in root.iter("testcase")}
    assert set(cases) == CHECKS, out
    assert not [n for n, c in cases.items() if c.find("skipped") is not None], out
    props = [(p.get("name"), p.get("value")) for p in root.iter("property")]
    assert ("bus", f"localbus:{bus} realtime") in props and ("dbc", "their.dbc") in props, props
    return (r, {n: c.find("failure").get("message") for n, c in cases.items() if c.find("failure") is not None},
            {n: c.find("error").get("message") or "" for n, c in cases.items() if c.find("error") is not None})


#: the suite's checks of timing: on a shared 2-core machine a CPU taken away for a tenth of a second puts a few
#: dozen command intervals out of tolerance (CI, stop 48: 63 of 2,992 against 60 allowed), the machine's doing,
#: not the TCU's.  A run that fails only these (beyond what the TCU must fail) is made again, at most
#: TIMING_ATTEMPTS runs in all; the last one must give exactly the expected verdicts.
TIMING_CHECKS = {"answers within three periods", "commands every period"}
TIMING_ATTEMPTS = 3


@pytest.mark.realtime
@pytest.mark.parametrize("tcu, fails, says", [
    (None, set(), None),
    ("keeps_demand.py --bus {bus}", {"no macro-slip", "uses the wet patch's adhesion"}, None),
    ("answers_late.py {scenario} --bus {bus}", CHECKS, "the TCU's commands came late"),
])
def test_the_example_suite_in_real_time_on_a_local_bus(tmp_path, tcu, fails, says):
    """Issue 37 item 8 in real time: the example suite (wet_patch, 3 s, their.dbc) with ``--hil-mode realtime`` on
    a local bus, SCHED_FIFO for the plant and the TCU (the suite's ``bus.rt_priority``; ``chrt`` for a TCU the
    plugin starts).  The built-in TCU passes all four checks; the one that keeps the demand fails the two
    adhesion checks and no other; the one that answers five periods late misses four deadlines in five (its
    answers come after them), so its run fails as a whole and every check with it, the JUnit failure saying
    the commands came late (without step counters a late answer is a missed deadline: docs/guide/verdicts.md).
    No case errors.

    The run is made again (``TIMING_ATTEMPTS`` runs in all) when its only failures beyond the expected ones
    are timing checks (``TIMING_CHECKS``), when the built-in TCU's every check failed on lateness alone, or
    when every check errored because the bench could not judge the TCU's timing (the plant itself began
    periods late: the plugin's own verdict that the run is no evidence): on a shared 2-core machine a CPU
    taken from the TCU for a tenth of a second is the machine's, not the suite's (docs/design/ci.md has the
    CI runs that showed it).  The last run's verdicts must be exactly the expected ones."""
    _sched_fifo_or_skip()
    for attempt in range(1, TIMING_ATTEMPTS + 1):
        r, failed, errored = _suite_in_real_time(tmp_path / f"run{attempt}", tcu)
        late = set(failed) == CHECKS and all(m.startswith("the TCU's commands came late") for m in failed.values())
        stalled = set(errored) == CHECKS and all("the bench could not judge" in m for m in errored.values())
        timing_only = bool(set(failed) - fails) and set(failed) - fails <= TIMING_CHECKS and not errored
        if not ((tcu is None and late) or stalled or timing_only) or attempt == TIMING_ATTEMPTS:
            break
        why = next(iter({**failed, **errored}.values()), "")
        print(f"real time, {tcu or 'built-in TCU'}, run {attempt}: "
              f"{'every check errored' if stalled else 'failed ' + ', '.join(sorted(failed))} ({why}); once more")
    out = r.stdout[-3000:] + r.stderr[-2000:]
    assert not errored, out
    assert set(failed) == fails, out
    for name, message in failed.items():
        assert says is None or message.startswith(says), message
    print(f"real time, {tcu or 'built-in TCU'}: {len(failed)} of 4 failed, {r.stdout.strip().splitlines()[-1]}")
