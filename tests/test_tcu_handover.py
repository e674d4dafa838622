"""The TCU runs the plant's scenario, provably, and a TCU process that fails says how (issue 49, items 1
and 3): real runs over real buses and real processes.

- The Python API hands the TCU child the resolved scenario (overrides included): the identification equals
  the command line's with the same ``--set`` (before: the child loaded the file without the overrides).
- A built-in TCU started on another scenario is refused before the first period, naming both digests.
- Through the pytest plugin, a ``--hil-tcu-cmd`` that cannot start is an *error* of the set-up within
  seconds with its exit code and stderr; one that dies mid-run is a *failure* named a crash, with its exit
  code; ten failing tests print a few lines each with ``--tb=short``.
"""
import json
import shutil
import subprocess
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path


from .conftest import SCENARIOS, hil_command, subprocess_env

pytest_plugins = ["pytester"]

FFCC_A = SCENARIOS / "ffcc_a.toml"
OVERRIDES = {"run.exchange_period_s": 0.002, "run.seed": 3, "run.duration_s": 1.2,
             "bus.lockstep_silence_s": 10.0}        # a loaded 2-core host can stall a node for a second


def _bus_dir() -> Path:
    """A local bus both sides open: a private directory with a path short enough for AF_UNIX."""
    return Path(tempfile.mkdtemp(prefix="hil-bus-"))


def test_the_api_hands_the_tcu_the_overrides_and_identifies_as_the_command_line(tmp_path):
    import hil

    api = hil.run(hil.load_scenario(FFCC_A, OVERRIDES), out_dir=tmp_path / "api", progress=False, bus="local")
    cli = subprocess.run(hil_command() + ["run", str(FFCC_A), "--bus", "local", "--out", str(tmp_path / "cli"),
                                          "--no-rrd", "--json"]
                         + [a for k, v in OVERRIDES.items() for a in ("--set", f"{k}={v}")],
                         capture_output=True, text=True, env=subprocess_env(), timeout=300)
    assert cli.returncode == 0, cli.stderr
    cli = json.loads(cli.stdout)
    keys = ("t_identified_s", "peak_mu", "peak_creep_kmh", "peak_mu_ci", "peak_creep_ci", "samples")
    assert {k: api.get(k) for k in keys} == {k: cli.get(k) for k in keys}
    # the overrides reached the TCU: its samples come every 2 ms (TcuSample steps of a 2 ms period)
    assert api["peak_ci_holds_truth"] is True and abs(api["peak_mu_err_percent"]) < 1.0, api


def test_a_sweep_point_on_a_tcu_process_identifies_as_the_api(tmp_path):
    """A one-point sweep (transport "process": plant and TCU processes on a local bus) on the same resolved
    scenario identifies as ``hil.run`` does: the point's TCU process is handed the scenario, not a file."""
    import hil

    sweep = tmp_path / "one.toml"
    sweep.write_text(f'name = "one"\nbase = {str(FFCC_A)!r}\ntransport = "process"\nseed = 3\n\n[set]\n'
                     + "".join(f'"{k}" = {v}\n' for k, v in OVERRIDES.items() if k != "run.seed")
                     + '\n[axes."run.mu_required"]\nvalues = [0.16]\n')
    r = subprocess.run(hil_command() + ["sweep", str(sweep), "--workers", "1", "--out", str(tmp_path / "sw"),
                                        "--json"], capture_output=True, text=True, env=subprocess_env(), timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    import pandas

    table = pandas.read_parquet(tmp_path / "sw" / "table")
    assert len(table) == 1 and table["error"].isna().all(), table.to_dict("records")
    point = json.loads(table["result_json"].iloc[0])
    api = hil.run(hil.load_scenario(FFCC_A, {**OVERRIDES, "run.mu_required": 0.16}), out_dir=tmp_path / "api",
                  progress=False, bus="local")
    keys = ("t_identified_s", "peak_mu", "peak_creep_kmh", "peak_mu_ci", "peak_creep_ci")
    assert {k: point.get(k) for k in keys} == {k: api.get(k) for k in keys}


def test_a_tcu_on_another_scenario_is_refused_before_the_first_period(tmp_path):
    bus = _bus_dir()
    env = subprocess_env()
    tcu = subprocess.Popen(hil_command() + ["tcu", str(FFCC_A), "--bus", f"localbus:{bus}", "--set", "run.seed=4",
                                            "--wait", "60"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        time.sleep(0.5)
        r = subprocess.run(hil_command() + ["run", str(FFCC_A), "--bus", f"localbus:{bus}", "--tcu", "external",
                                            "--out", str(tmp_path), "--no-rrd", "--json"],
                           capture_output=True, text=True, env=env, timeout=120)
    finally:
        tcu.terminate()
        tcu.wait(30)
        shutil.rmtree(bus, ignore_errors=True)
    assert r.returncode == 2, r.stderr
    from hil import load_scenario
    mine = load_scenario(FFCC_A).digest[:16]
    theirs = load_scenario(FFCC_A, {"run.seed": 4}).digest[:16]
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("hil run: error: the TCU runs another scenario") and mine in line and theirs in line, line


def _plugin_session(pytester, tests: str, tcu_cmd: str, bus: Path, *extra):
    pytester.makepyfile(test_unit=tests)
    t0 = time.monotonic()
    result = pytester.runpytest_subprocess("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus",
                                           f"localbus:{bus}", "--hil-tcu", "external", "--hil-tcu-cmd", tcu_cmd,
                                           "--hil-out", str(pytester.path / "out"),
                                           "--junitxml", str(pytester.path / "j.xml"), *extra)
    return result, time.monotonic() - t0


def _case_times(path) -> list[float]:
    return [float(c.get("time")) for c in ET.parse(path).getroot().iter("testcase")]


def test_a_tcu_command_with_a_typo_is_an_error_within_seconds_with_its_exit_code(pytester):
    bus = _bus_dir()
    try:
        result, _ = _plugin_session(pytester, f"""
def test_answers(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}})
""", "hil-tuc --bus {bus}", bus)
    finally:
        shutil.rmtree(bus, ignore_errors=True)
    result.assert_outcomes(errors=1)
    out = result.stdout.str()
    assert "the TCU process exited with code 127 before it joined the bus" in out, out
    assert "not found" in out, out                         # the shell's own line, from the command's stderr
    assert max(_case_times(pytester.path / "j.xml")) < 10.0       # not the 60 s start-up timeout
    props = {p.get("name"): p.get("value") for p in ET.parse(pytester.path / "j.xml").getroot().iter("property")}
    assert props["tcu_under_test"] == f"external: hil-tuc --bus localbus:{bus}"     # the template filled in


CRASHING_TCU = """import os, sys
import hil.tcu_node as tcu_node

answer = tcu_node.TcuNode.handle


def handle(self, msg, *args, **kwargs):      # the built-in TCU, which dies at step 500 as a segfault would
    replies = answer(self, msg, *args, **kwargs)
    if self.last_step >= 500:
        sys.stderr.write("segfault in the control task (simulated)\\n")
        sys.stderr.flush()
        os._exit(139)
    return replies


tcu_node.TcuNode.handle = handle
sys.exit(tcu_node.main(sys.argv[1:]))
"""


def test_a_tcu_that_dies_mid_run_is_a_failure_named_a_crash_with_its_exit_code(pytester):
    """The built-in TCU on the run's exact scenario (``{handover}``), dying at step 500 of a 3 s run."""
    import sys

    script = pytester.path / "crashing_tcu.py"
    script.write_text(CRASHING_TCU)
    bus = _bus_dir()
    try:
        result, wall = _plugin_session(pytester, f"""
def test_answers(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 3.0}})
""", f"{sys.executable} {script} --handover {{handover}} --bus {{bus}}", bus)
    finally:
        shutil.rmtree(bus, ignore_errors=True)
    result.assert_outcomes(failed=1)
    out = result.stdout.str()
    assert "the TCU fell silent or died: the TCU process exited with code 139 at step 50" in out, out
    assert "(a crash)" in out and "segfault in the control task (simulated)" in out, out


def test_ten_failing_tests_print_a_few_lines_each(pytester):
    """A TCU that never answers: ten tests of one run fail with the same verdict, each in at most 20 lines
    with ``--tb=short`` (before: about 330 lines each, growing as the cached exception was raised again)."""
    tests = "\n".join(f"""
def test_{i}(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0, "bus.startup_timeout_s": 1.0}})
""" for i in range(10))
    bus = _bus_dir()
    try:
        result, _ = _plugin_session(pytester, tests, "sleep 27.1828", bus, "--tb=short")
    finally:
        shutil.rmtree(bus, ignore_errors=True)
    result.assert_outcomes(failed=10)
    lines = result.stdout.lines
    starts = [i for i, ln in enumerate(lines) if ln.startswith("_____") and " test_" in ln]
    ends = starts[1:] + [next(i for i, ln in enumerate(lines) if "short test summary" in ln or
                              ln.startswith("- generated xml"))]
    sizes = [b - a for a, b in zip(starts, ends)]
    assert len(sizes) == 10 and max(sizes) <= 20, (sizes, "\n".join(lines))
    assert "Traceback" not in result.stdout.str()
