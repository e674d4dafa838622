"""End to end: ``hil run`` as a user runs it, the MCAP it writes read back with the mcap library,
and a run killed with SIGKILL."""
import json
import os
import signal
import subprocess
import sys
import time

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from hil.log.read import read_log

from .conftest import SCENARIOS, hil_command, kill_run_when_log_reaches, subprocess_env

TOPICS = {"/plant/state", "/plant/sensor", "/tcu/command", "/tcu/observer", "/tcu/status", "/tcu/identification",
          "/run/summary"}


@pytest.fixture(scope="module")
def ffcc_a_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    r = subprocess.run(hil_command() + ["run", "scenarios/ffcc_a.toml", "--bus", "inprocess", "--seed", "3",
                                        "--out", str(out), "--json"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout), out


def test_json_has_the_promised_keys(ffcc_a_run):
    s, out = ffcc_a_run
    for key in ("scenario", "strategy", "seed", "bus", "identified", "t_fault_s", "t_serious_s", "t_identified_s",
                "rt_percent", "params", "mse", "rmse", "mae", "r2", "peak_mu_err_percent", "peak_creep_err_percent",
                "corrections", "mcap"):
        assert key in s, key
    assert s["scenario"] == "ffcc_a" and s["strategy"] == "gp" and s["seed"] == 3
    assert len(s["params"]) == 5
    # T_det is tens of milliseconds, as the paper's figures imply
    assert 0.03 < s["t_serious_s"] - s["t_fault_s"] < 0.12
    if s["identified"]:
        assert s["t_identified_s"] > s["t_fault_s"]
        assert s["rt_percent"] == pytest.approx((s["t_identified_s"] - s["t_fault_s"])
                                                / (s["t_serious_s"] - s["t_fault_s"]) * 100)
    assert s["mcap"].endswith("ffcc_a-gp-3.mcap")


def test_mcap_reads_back_with_the_standard_reader(ffcc_a_run):
    s, out = ffcc_a_run
    path = out / "ffcc_a-gp-3.mcap"
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {ch.topic for ch in summary.channels.values()}
        assert TOPICS <= topics
        assert all(summary.schemas[ch.schema_id].encoding == "protobuf" for ch in summary.channels.values())
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert {"scenario", "versions", "run", "summary"} <= set(meta)
        assert "[curves.fault]" in meta["scenario"]["toml"]
        assert json.loads(meta["summary"]["json"]) == s
        states = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/plant/state"])]
    steps = [m.step for m in states]
    assert steps == list(range(len(steps))) and len(steps) == 1000
    stages = [m.stage for m in states]
    assert stages.index("serious") * 1e-3 == pytest.approx(s["t_serious_s"])
    # every identification event the summary counts is in the log
    log = read_log(path)
    assert log.complete
    events = log.topic("/tcu/identification")
    assert sum(e.kind == "correction" for e in events) == s["corrections"]
    assert [list(e.params) for e in events][-1] == pytest.approx(s["params"])


def test_sigkill_leaves_a_readable_prefix(tmp_path):
    path = tmp_path / "ffcc_a-gp-1.mcap"
    kill_run_when_log_reaches(["run", str(SCENARIOS / "ffcc_a.toml"), "--bus", "inprocess", "--out", str(tmp_path),
                               "--set", "run.duration_s=60", "--set", "run.fault_time_s=50"], path, 400_000)
    log = read_log(path)
    assert not log.complete
    states = log.topic("/plant/state")
    assert len(states) > 200          # 400 kB of a run hold several hundred periods
    # what was read back is a gap-free prefix of the run
    assert [m.step for m in states] == list(range(len(states)))
    assert "scenario" in log.metadata


@pytest.mark.parametrize("out, says", [("run.mcap", "names a directory for the logs, not a log file"),
                                       ("/proc/no/such/dir", "cannot create the directory")])
def test_an_unusable_out_is_one_line_and_writes_nothing(tmp_path, out, says):
    r = subprocess.run(hil_command() + ["run", str(SCENARIOS / "ffcc_a.toml"), "--bus", "inprocess", "--out", out],
                       cwd=tmp_path, capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 2 and says in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_log_names_keep_plant_and_reality_runs_apart_and_stay_inside_out(tmp_path):
    """A --reality run never takes the nominal run's log name, and a scenario name with path parts
    cannot put the log outside --out."""
    scenario = tmp_path / "s.toml"
    text = (SCENARIOS / "ffcc_a.toml").read_text()
    assert 'name = "ffcc_a"' in text
    scenario.write_text(text.replace('name = "ffcc_a"', 'name = "../../escaped/x"'))
    out = tmp_path / "logs"
    names = []
    for extra in ([], ["--reality", "resistance:factor=1.2"]):
        r = subprocess.run(hil_command() + ["run", str(scenario), "--bus", "inprocess", "--out", str(out), "--json",
                                            "--no-rrd", "--set", "run.duration_s=0.1", "--set", "run.fault_time_s=0.05",
                                            *extra], capture_output=True, text=True, env=subprocess_env(), timeout=120)
        assert r.returncode == 0, r.stderr
        names.append(json.loads(r.stdout)["mcap"])
    assert len(set(names)) == 2 and "replacing" not in r.stderr
    assert all(str(p).startswith(str(out) + "/") and "/" not in str(p)[len(str(out)) + 1:] for p in names), names
    assert "resistance" not in names[1] and "-real-" in names[1]
    assert not (tmp_path.parent / "escaped").exists()


@pytest.mark.parametrize("delay_s", [0.15, 0.25, 0.4, 0.55, 0.7])
def test_ctrl_c_during_start_up_is_one_line_not_a_traceback(tmp_path, delay_s):
    """SIGINT while hil is still importing numpy, scipy and casadi (the first ~second; a Ctrl-C inside
    scipy's HiGHS extension comes out as an ImportError caused by the KeyboardInterrupt)."""
    p = subprocess.Popen(hil_command() + ["run", str(SCENARIOS / "ffcc_a.toml"), "--bus", "inprocess"], cwd=tmp_path,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env())
    time.sleep(delay_s)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].endswith("interrupted")


@pytest.mark.parametrize("delay_s", [0.2, 0.5, 0.8, 1.2, 2.0])
def test_sigterm_of_the_tcu_process_is_one_line_not_a_traceback(tmp_path, delay_s):
    """The plant ends its TCU process with SIGTERM (a failed run, e.g. a full disk); whenever it lands,
    while Python starts (the default action: killed by the signal), while the TCU imports numpy, scipy
    and numba, or while it waits on the bus, the TCU prints no traceback into the run's stderr."""
    from hil.bus.localbus import create_channel, remove_channel

    channel = create_channel()
    try:
        p = subprocess.Popen([sys.executable, "-m", "hil.tcu_node", str(SCENARIOS / "ffcc_a.toml"), "--bus",
                              f"localbus:{channel}", "--wait", "60"], cwd=tmp_path, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=subprocess_env())
        time.sleep(delay_s)
        p.send_signal(signal.SIGTERM)
        _, err = p.communicate(timeout=120)
    finally:
        remove_channel(channel)
    print(f"exit {p.returncode}: {err.strip()[-300:]}")
    assert p.returncode in (130, -signal.SIGTERM), err
    assert "Traceback" not in err, err
    if p.returncode == 130:
        assert err.strip().splitlines()[-1].startswith("hil tcu: interrupted"), err


TCU_TERMINATED_IN_A_CALLBACK = """
import ctypes, os, signal, sys, time
import hil.tcu_node as tcu_node
serve = tcu_node.serve
class Bus:                          # the TCU's bus, unchanged but for one wait
    def __init__(self, bus):
        self.bus, self.t0, self.sent = bus, time.monotonic(), False
    def __getattr__(self, name):
        return getattr(self.bus, name)
    def recv(self, timeout=None):
        if not self.sent and time.monotonic() > self.t0 + 0.3:
            self.sent = True
            def callback():         # the SIGTERM lands in here: its interrupt cannot be raised
                os.kill(os.getpid(), signal.SIGTERM)
                sum(range(100000))
            ctypes.CFUNCTYPE(None)(callback)()
            print("after the callback", time.monotonic(), file=sys.stderr, flush=True)
        return self.bus.recv(timeout)
tcu_node.serve = lambda bus, node, **kw: serve(Bus(bus), node, **kw)
sys.exit(tcu_node.main(sys.argv[1:]))
"""


def test_a_sigterm_the_tcu_could_not_raise_inside_a_callback_still_ends_it_as_interrupted(tmp_path):
    """The plant's SIGTERM landing while the TCU's main thread is inside a ctypes callback (numba
    compiling): the interrupt cannot unwind there.  The TCU still ends at its loop's next turn, with the
    one line and exit 130, not a traceback and not after waiting out its start-up timeout (60 s here)."""
    from hil.bus.localbus import create_channel, remove_channel

    channel = create_channel()
    try:
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-c", TCU_TERMINATED_IN_A_CALLBACK, str(SCENARIOS / "ffcc_a.toml"),
                            "--bus", f"localbus:{channel}", "--wait", "60"], cwd=tmp_path, capture_output=True,
                           text=True, env=subprocess_env(), timeout=120)
        took_s = time.monotonic() - t0
    finally:
        remove_channel(channel)
    assert "after the callback" in r.stderr, r.stderr         # the interrupt did not unwind the callback
    assert r.returncode == 130, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.strip().splitlines()[-1] == "hil tcu: interrupted", r.stderr
    assert took_s < 50, took_s


def test_an_interrupt_something_swallowed_still_stops_the_run():
    """A Ctrl-C that a library swallows while hil imports (an optional import that catches the
    ImportError the interrupt became: seen once in CI, exit 0 after a full run) is remembered by the
    command's handler, and the run does not start (``interrupts_between_writes``)."""
    from hil.cli import _Interrupts
    from hil.log.record import interrupts_between_writes

    handler = _Interrupts()
    old = signal.signal(signal.SIGINT, handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            handler(signal.SIGINT, None)              # the interrupt ...
        with interrupts_between_writes():             # ... swallowed (caught here): nothing remembers it but
            pass                                      # the handler; a run would start only if it was not seen
        raise AssertionError("a run started although Ctrl-C was pressed")
    except KeyboardInterrupt:
        assert signal.getsignal(signal.SIGINT) is handler     # the run's own handlers put back
    finally:
        signal.signal(signal.SIGINT, old)


def test_an_interrupt_swallowed_during_a_run_still_ends_the_command_as_interrupted():
    """A Ctrl-C during the run that something catches as KeyboardInterrupt (seen in CI: SIGINT 0.7 s
    into an in-process run, which went on to exit 0) is still told to the command's handler, so
    ``hil`` ends as interrupted (exit 130) once the run returns."""
    from hil.cli import _Interrupts
    from hil.log.record import interrupts_between_writes

    handler = _Interrupts()
    old = signal.signal(signal.SIGINT, handler)
    try:
        with interrupts_between_writes():
            try:
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.5)
                raise AssertionError("no KeyboardInterrupt within 0.5 s of SIGINT")
            except KeyboardInterrupt:
                pass                                  # swallowed, as a library might
        assert handler.interrupted
        assert signal.getsignal(signal.SIGINT) is handler
    finally:
        signal.signal(signal.SIGINT, old)


def test_an_interrupt_raised_inside_a_ctypes_callback_is_remembered_not_printed():
    """SIGINT landing while numba compiles runs the handler inside llvmlite's ctypes callback, where
    Python cannot pass the KeyboardInterrupt on: it went to ``sys.unraisablehook``, which printed
    "Exception ignored ... Traceback" on a run's stderr (seen in CI, Ctrl-C 0.7 s into ``hil run``).
    Under the hook the commands install it is remembered instead; any other unraisable error is
    still printed.  A real ctypes callback in a fresh interpreter."""
    script = """
import ctypes, os, signal
from hil.errors import remember_unraisable_interrupts
seen = []
remember_unraisable_interrupts(lambda: seen.append("interrupt"))
def handler(signum, frame):
    raise KeyboardInterrupt
signal.signal(signal.SIGINT, handler)
def callback():
    os.kill(os.getpid(), signal.SIGINT)
    sum(range(100000))              # the handler runs here, inside the callback
ctypes.CFUNCTYPE(None)(callback)()
class Broken:
    def __del__(self):
        raise ValueError("a real unraisable error")
Broken()
print(seen)
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=subprocess_env(),
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "['interrupt']", (r.stdout, r.stderr)
    assert "KeyboardInterrupt" not in r.stderr, r.stderr
    assert "ValueError: a real unraisable error" in r.stderr, r.stderr


@pytest.mark.parametrize("name, refused", [("../../elsewhere/pwned", False), ("{tmp}/abs/pwned", False),
                                           ("a\\u0000b", True), ("../" * 100, True), ("x" * 300, False),
                                           ("/../..", True)])
def test_no_scenario_name_puts_a_file_outside_out(tmp_path, name, refused):
    """Path parts, an absolute path, a NUL, 300 characters: the logs (.mcap and .rrd) land in --out under
    a slug of the name, or the name is refused in one line and nothing is written."""
    scenario = tmp_path / "s.toml"
    name = name.replace("{tmp}", str(tmp_path))
    scenario.write_text((SCENARIOS / "ffcc_a.toml").read_text().replace('name = "ffcc_a"', f'name = "{name}"'))
    out = tmp_path / "a" / "b" / "out"
    (tmp_path / "a").mkdir()
    r = subprocess.run(hil_command() + ["run", str(scenario), "--bus", "inprocess", "--out", str(out), "--seed", "5",
                                        "--set", "run.duration_s=0.2", "--set", "run.fault_time_s=0.1"],
                       cwd=tmp_path / "a", capture_output=True, text=True, env=subprocess_env(), timeout=150)
    written = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file())
    if refused:
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert "name" in r.stderr and written == [scenario.relative_to(tmp_path)]
        return
    assert r.returncode == 0, r.stderr
    logs = [p for p in written if p.parts[:3] == ("a", "b", "out")]
    assert sorted(p.suffix for p in logs) == [".mcap", ".rrd"], written
    assert set(written) == {scenario.relative_to(tmp_path), *logs}, written
    stem = logs[0].stem
    assert stem.endswith("-gp-5") and len(stem) <= 60 + len("-gp-5") and ".." not in stem


def test_the_text_summary_fits_a_terminal_and_says_what_the_json_says(ffcc_a_run):
    """Issue 51: ``hil run``'s text is built from the typed summary (``hil.run_summary``) and every line is
    within 100 characters.  The real run's summary, then the same summary with the long branches a run can
    reach switched on (three reality effects, a real-time run whose misses have both causes, rejected
    frames, open intervals that miss the truth, unmapped and suspicious frames): each figure still printed,
    in the words the docs and the tests read, a longer line continued further in."""
    import io

    from hil.commands.run import print_summary
    from hil.terminal import WIDTH

    s, _ = ffcc_a_run

    def text_of(summary):
        buf = io.StringIO()
        print_summary(summary, file=buf)
        text = buf.getvalue()
        assert max(len(line) for line in text.splitlines()) <= WIDTH == 100, text
        return text, " ".join(line.strip() for line in text.splitlines())

    text, flat = text_of(s)
    assert text.splitlines()[0] == f"scenario ffcc_a  strategy gp  seed 3  bus inprocess  plant {s['plant']}" + (
        "  frames not authenticated" if s.get("frame_auth") == "off" else "  frames authenticated")
    assert f"RT {s['rt_percent']:.1f} % after {s['corrections']} corrections" in flat
    assert "params (l0, l1, l2, t1, t2): " + ", ".join(f"{x:.5g}" for x in s["params"]) in flat
    assert f"log: {s['mcap']}" in flat
    long = {**s, "mode": "realtime", "missed_deadlines": 1234, "missed_deadlines_plant_started_late": 1000,
            "missed_deadlines_cpu_away": 234, "jitter_p99_us": 61.7,
            "rejected_frames": {"crc": 3, "counter": 4}, "tcu_rejected_frames": {"stale": 5},
            "reality": {"load_transfer": {"bogie_height_m": 1.5}, "sensor_delay": {"delay_ms": 3.25},
                        "power_limit": {"max_power_w": 1.2e6, "ratio": 1.04}},
            "identified": False, "unconfirmed": True, "peak_interval_open": True, "peak_ci_holds_truth": False,
            "peak_mu_ci": [0.14, 0.16], "peak_creep_ci": [1.1, 9.9],
            "unmapped_ids": {f"0x{i:03X}": 10 + i for i in range(0x300, 0x30C)},
            "suspicious": {"replayed": 2, "forged_counter": 7, "unknown_sender": 1}}
    text, flat = text_of(long)
    for said in ("reality: load_transfer(bogie_height_m=1.5); sensor_delay(delay_ms=3.25); "
                 "power_limit(max_power_w=1200000.0, ratio=1.04)",
                 f"UNCONFIRMED: the TCU gave up after {s['corrections']} corrections", "its best estimate:",
                 "peak mu 0.1400 .. 0.1600, peak creep 1.100 .. 9.900 km/h",
                 "(open: the peak may lie past the creeps seen", "its 90 % intervals MISS the true peak",
                 "missed deadlines 1234 (1000 in periods the plant itself began past the deadline: a stall of its "
                 "process or CPU; 234 with a CPU taken away by the machine), jitter p99 62 us; rejected frames: "
                 "plant 7, TCU 5",
                 "frames of ids the mapping does not name (not acted on): 0x300 x778, 0x301 x779",
                 "0x30B x789", "suspicious frames (another node on the bus?): forged_counter x7, replayed x2, "
                 "unknown_sender x1"):
        assert said in flat, (said, text)
    assert any(line.startswith("      ") for line in text.splitlines())       # a long line continued further in
