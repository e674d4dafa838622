"""The pytest plugin in real pytest sessions (``pytester``, the plugin named with ``-p hil.pytest_plugin``
as in a tree that is not installed): a passing and a failing suite over real 1-second in-process runs,
their JUnit XML parsed and validated against Jenkins' junit-10.xsd (tests/data/junit-10.xsd, from pytest
9.2.0's source distribution on PyPI, testing/example_scripts/junit-10.xsd; MIT, Gregory Boissinot),
attachments, a bench error reported as an error, a missing bus as a skip (an error under CI=true), and a
malformed ``[[check]]`` table as one line."""
import importlib
import re
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from .conftest import ROOT, SCENARIOS, hil_command, subprocess_env

pytest_plugins = ["pytester"]

XSD = ROOT / "tests" / "data" / "junit-10.xsd"
FFCC_A = SCENARIOS / "ffcc_a.toml"


@pytest.fixture(autouse=True, scope="module")
def _loaded():
    """What the sessions import, imported here first: pytester's in-process sessions remove the modules
    they imported when they end, and numpy cannot be imported twice in one process."""
    for name in ("matplotlib.pyplot", "hil.checks.offline", "hil.exchange", "hil.view"):
        importlib.import_module(name)


def _validated(path):
    from lxml import etree

    schema = etree.XMLSchema(etree.parse(str(XSD)))
    doc = etree.parse(str(path))
    assert schema.validate(doc), schema.error_log
    return ET.parse(str(path)).getroot()


def _session(pytester, *args):
    return pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", "inprocess",
                              "--hil-out", str(pytester.path / "hil-out"), "--junitxml",
                              str(pytester.path / "junit.xml"), *args)


def test_the_plugin_module_imports_only_pytest_and_the_standard_library():
    code = ("import sys, hil.pytest_plugin; print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('hil', 'numpy', 'plant', 'identifier', 'cantools', 'mcap', 'matplotlib')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert r.stdout.strip() == "['hil', 'hil.pytest_plugin']", r.stdout + r.stderr
    assert '"hil.pytest_plugin" = "hil.pytest_plugin"' in (ROOT / "pyproject.toml").read_text()


@pytest.mark.parametrize("with_p", [False, True])
def test_the_entry_point_loads_the_plugin_and_minus_p_does_not_register_it_twice(tmp_path, with_p):
    """Installed (here: a dist-info with pyproject.toml's pytest11 entry point, on the path), the plugin loads
    by itself; ``-p hil.pytest_plugin`` as well must not register the module a second time (pluggy's
    "already registered under a different name" when the entry point's name differs from the module's)."""
    import tomllib

    eps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["pytest11"]
    site = tmp_path / "site"
    info = site / "railway_hil_probe-0.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: railway-hil-probe\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text("[pytest11]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()))
    (tmp_path / "test_x.py").write_text("def test_x(hil_run):\n    assert callable(hil_run)\n")
    env = subprocess_env(PYTHONPATH=f"{ROOT}:{site}")
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *(["-p", "hil.pytest_plugin"]
                        if with_p else []), "test_x.py"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "1 passed" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]


def test_the_example_suite_passes_with_the_builtin_tcu_running_once(pytester):
    """scenarios/suites: the Python tests and the test_*.toml checks share one run (cached)."""
    for f in (SCENARIOS / "suites").iterdir():
        if f.suffix in (".py", ".toml") and f.stem == "test_ffcc_a":     # test_their_tcu.toml: tests/test_mapping.py
            pytester.makefile(f.suffix, **{f.stem: f.read_text().replace('"../ffcc_a.toml"', f'"{FFCC_A}"')
                                           .replace('Path(__file__).resolve().parent.parent / "ffcc_a.toml"',
                                                    f'Path({str(FFCC_A)!r})')})
    result = _session(pytester)
    result.assert_outcomes(passed=7)
    logs = list((pytester.path / "hil-out").rglob("*.mcap"))
    assert len(logs) == 1, logs                                        # one run for seven tests
    root = _validated(pytester.path / "junit.xml")
    props = {p.get("name"): p.get("value") for p in root.iter("property")}
    assert re.fullmatch(r"[0-9a-f]{64}", props["dbc_sha256"]) and props["railway_hil_version"] == "0.1.0"
    assert props["tcu_under_test"] == "builtin (hil.tcu_node)" and props["bus"] == "inprocess lockstep"
    names = [c.get("name") for c in root.iter("testcase")]
    assert "1-slip detected within 50 ms" in names and "test_the_slip_is_answered_and_the_curve_identified" in names


FAILING = f"""
from hil.checks import in_range, limit, require

def test_slip_is_held(hil_run):
    run = hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}})
    require(run, limit("t_identified_s", hi=0.7, req="ID-1"),
            in_range("/plant/state.creep_speed_kmh", hi=1.0, during="fault", req="ADH-1"),
            in_range("TcuStatus.MuHat", 0.2, 0.3, during=("fault", 0.0, 0.1), valid="TcuStatus.ObserverValid"))

def test_same_run_again(hil_run):
    assert hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}}).summary["identified"]
"""


def test_a_failing_suite_lists_every_failed_check_with_figures_log_and_command(pytester):
    pytester.makepyfile(test_fails=FAILING)
    result = _session(pytester)
    result.assert_outcomes(passed=1, failed=1)
    out = result.stdout.str()
    assert "2 of 3 checks failed:" in out
    assert re.search(r"\[ADH-1\] /plant/state\.creep_speed_kmh outside \[-inf, 1\] from fault\+0 ms on: first "
                     r"\d\.\d{3} s \(\S+ km/h\), worst \S+ km/h at \d\.\d{3} s, \d+ ms in violation", out), out
    root = _validated(pytester.path / "junit.xml")
    case = next(c for c in root.iter("testcase") if c.get("name") == "test_slip_is_held")
    assert case.find("failure") is not None and case.find("error") is None
    text = case.findtext("system-out")
    pngs = re.findall(r"\[\[ATTACHMENT\|(.+?)\]\]", text)
    assert len(pngs) == 2 and all(open(p, "rb").read(8) == b"\x89PNG\r\n\x1a\n" for p in pngs), text
    assert re.search(r"^log: .+\.mcap$", text, re.M) and re.search(r"^recording: .+\.rrd$", text, re.M), text
    command = re.search(r"^reproduce: (pytest .+)$", text, re.M).group(1)
    assert command.startswith(f"pytest {pytester.path / 'test_fails.py'}::test_slip_is_held -p hil.pytest_plugin")
    assert command.endswith("--hil-bus inprocess --hil-mode lockstep --hil-tcu builtin"), command
    assert re.search(r"^re-judge: hil check \S+\.mcap \S+/test_slip_is_held\.checks\.toml$", text, re.M), text


def _printed(text, label):
    """The command printed on a ``label:`` line of a failure's output, as argv (``pytest``/``hil`` made the
    interpreter's own)."""
    import shlex

    argv = shlex.split(re.search(rf"^{label}: (.+)$", text, re.M).group(1))
    return ([sys.executable, "-m", "pytest"] if argv[0] == "pytest" else hil_command()) + argv[1:]


def test_the_printed_reproduce_and_re_judge_commands_give_the_same_verdicts(pytester):
    """Issue 49 item 4: the failure's ``reproduce:`` command, run as printed (a new pytest process), fails the
    same test with the same FAIL lines; its ``re-judge:`` command (``hil check`` on the log, by the checks the
    test wrote in Python, exported beside the log) gives each check the verdict pytest gave it."""
    pytester.makepyfile(test_fails=FAILING)
    result = _session(pytester)
    result.assert_outcomes(passed=1, failed=1)
    root = _validated(pytester.path / "junit.xml")
    text = next(c for c in root.iter("testcase") if c.get("name") == "test_slip_is_held").findtext("system-out")
    fails = sorted(ln for ln in text.splitlines() if ln.startswith("FAIL "))
    assert len(fails) == 2, text

    again = subprocess.run(_printed(text, "reproduce") + ["-p", "no:cacheprovider", "--hil-out",
                                                          str(pytester.path / "again"), "-rf"],
                           capture_output=True, text=True, env=subprocess_env(), timeout=300, cwd="/")
    assert again.returncode == 1 and "1 failed" in again.stdout, again.stdout[-3000:] + again.stderr[-2000:]
    assert "test_same_run_again" not in again.stdout                     # the one test, by its node id
    assert sorted(ln.strip() for ln in again.stdout.splitlines() if ln.strip().startswith("FAIL ")) == fails

    judged = subprocess.run(_printed(text, "re-judge"), capture_output=True, text=True, env=subprocess_env(),
                            timeout=120)
    assert judged.returncode == 1, judged.stdout + judged.stderr
    assert sorted(ln for ln in judged.stdout.splitlines() if ln.startswith("FAIL ")) == fails, judged.stdout
    assert "1 of 3 checks passed" in judged.stdout


def test_a_bench_error_is_an_error_not_a_failure(pytester):
    """A plant that diverges (resistance x 1e300) is the bench's fault: JUnit <error>, never <failure>."""
    pytester.makepyfile(test_bench=f"""
def test_diverges(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}}, reality=["resistance:factor=1e300"])
""")
    result = _session(pytester)
    result.assert_outcomes(errors=1)
    assert "the bench could not judge: the plant failed" in result.stdout.str()
    root = _validated(pytester.path / "junit.xml")
    case = next(root.iter("testcase"))
    assert case.find("error") is not None and case.find("failure") is None
    assert root[0].get("errors") == "1" and root[0].get("failures") == "0"
    # hil check on the log it left: the bench's error code and its line, not a fail
    log = next((pytester.path / "hil-out").rglob("*.mcap"))
    r = subprocess.run(hil_command() + ["check", str(log), str(SCENARIOS / "suites" / "test_ffcc_a.toml"),
                                        "--junitxml", str(pytester.path / "check.xml")],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 2 and "the run did not finish" in r.stderr and "Traceback" not in r.stderr, r.stderr
    suite = _validated(pytester.path / "check.xml")[0]
    # one judge (issue 49 item 8): each of the file's five checks an error, as the plugin reports each
    assert suite.get("errors") == "5" and suite.get("failures") == "0" and suite.get("tests") == "5"
    assert all("the run did not finish" in e.get("message") for e in suite.iter("error"))


@pytest.mark.parametrize("ci", ["", "true"])
def test_a_named_bus_that_cannot_open_is_an_error_never_a_skip(pytester, monkeypatch, ci):
    """A bus named with --hil-bus that does not open here is an error of the set-up, with or without CI=true
    (a green suite that ran nothing is worse than a red one); the line names the option and what is there."""
    monkeypatch.setenv("CI", ci)
    pytester.makepyfile(test_bus=f"""
def test_on_a_bus(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}})
""")
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus",
                                "socketcan:hilnone0", "--hil-out", str(pytester.path / "out"), "-rs")
    result.assert_outcomes(errors=1)
    assert "--hil-bus socketcan:hilnone0:" in result.stdout.str()
    assert "a bus named explicitly must open" in result.stdout.str()


def test_a_malformed_check_table_is_one_line_naming_the_file_and_field(pytester):
    pytester.makefile(".toml", test_bad=f'scenario = "{FFCC_A}"\n\n[[check]]\nname = "fast"\nkind = "responds"\n'
                                         'trigger = "fault"\ncondition = "TcuStatus.Stage >= 1"\nwithin_s = "soon"\n')
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider")
    result.assert_outcomes(errors=1)
    lines = [ln for ln in result.stdout.lines if "test_bad.toml: [[check]] 1 (fast): field 'within_s'" in ln]
    assert lines and "expected a number, got 'soon'" in lines[0], result.stdout.str()
    assert "Traceback" not in result.stdout.str()


def test_a_silent_tcu_is_a_failure_and_hil_check_fails_its_log(pytester):
    """An external TCU that never answers (the command started for the run sleeps): a *fail* of the TCU,
    JUnit <failure>; the command is stopped after the run; ``hil check`` on the log it left exits 1."""
    marker = "31.4159"
    pytester.makepyfile(test_silent=f"""
def test_answers(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0, "bus.startup_timeout_s": 2.0}})
""")
    # a local bus both sides open: a directory of this user's, mode 700, with a path short enough for AF_UNIX
    bus = Path(tempfile.mkdtemp(prefix="hil-bus-"))
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", f"localbus:{bus}",
                                "--hil-tcu", "external", "--hil-tcu-cmd", f"sleep {marker}",
                                "--hil-out", str(pytester.path / "out"), "--junitxml", str(pytester.path / "j.xml"), "-rs")
    result.assert_outcomes(failed=1)
    assert "the TCU fell silent or died: no TCU answered within 2 s" in result.stdout.str()
    root = _validated(pytester.path / "j.xml")
    case = next(root.iter("testcase"))
    assert case.find("failure") is not None and case.find("error") is None
    assert f"--hil-tcu external --hil-tcu-cmd 'sleep {marker}'" in case.findtext("system-out")
    props = {p.get("name"): p.get("value") for p in root.iter("property")}
    assert props["tcu_under_test"] == f"external: sleep {marker}"
    sleeping = [p for p in Path("/proc").glob("[0-9]*") if _cmdline(p) == f"sleep {marker}"]
    assert not sleeping, "the TCU command was not stopped after the run"
    log = next((pytester.path / "out").rglob("*.mcap"))
    r = subprocess.run(hil_command() + ["check", str(log), str(SCENARIOS / "suites" / "test_ffcc_a.toml")],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    assert r.stdout.startswith("FAIL run: the TCU fell silent or died: no TCU answered within 2 s"), r.stdout
    shutil.rmtree(bus, ignore_errors=True)


def test_a_tcu_command_on_a_bus_it_cannot_join_is_one_line_before_any_run(pytester):
    """``local`` is a new private bus per run: a TCU started by --hil-tcu-cmd could never join it (it would
    open its own), so the session says so at once instead of waiting out the start-up timeout."""
    pytester.makepyfile(test_join=f"""
def test_answers(hil_run):
    hil_run({str(FFCC_A)!r}, set={{"run.duration_s": 1.0}})
""")
    t0 = time.monotonic()
    result = pytester.runpytest("-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "--hil-bus", "local",
                                "--hil-tcu", "external", "--hil-tcu-cmd", "sleep 27.18",
                                "--hil-out", str(pytester.path / "out"))
    result.assert_outcomes(errors=1)
    assert "--hil-tcu-cmd with --hil-bus local: that bus is opened anew by each run" in result.stdout.str()
    assert "Traceback" not in result.stdout.str()
    assert not list((pytester.path / "out").rglob("*.mcap"))          # refused before any run
    print(f"refused after {time.monotonic() - t0:.1f} s")


def _cmdline(proc_dir) -> str:
    try:
        return (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
    except OSError:
        return ""


def test_twenty_checks_over_five_one_second_scenarios_run_each_scenario_once(pytester):
    """Issue 37's target: a suite of 20 checks (as data, 4 per file) over 5 one-second scenarios (FFCC-a and
    FFCC-b at different seeds and demands) runs each scenario once; the cost of judging each run's log by
    its 4 checks is printed (the target, < 1 s per run, is a speed figure: measured, not asserted)."""
    import time

    from hil.checks.run import Run
    from hil.checks.spec import judge, load_checks

    specs = [("ffcc_a", 1, 0.16), ("ffcc_a", 2, 0.158), ("ffcc_b", 1, None), ("ffcc_b", 3, None), ("ffcc_a", 4, 0.162)]
    for i, (name, seed, mu) in enumerate(specs):
        sets = f'"run.duration_s" = 1.0\n"run.seed" = {seed}\n' + (f'"run.mu_required" = {mu}\n' if mu else "")
        pytester.makefile(".toml", **{f"test_s{i}": f'scenario = "{SCENARIOS / (name + ".toml")}"\n[set]\n{sets}\n'
                                     '[[check]]\nname = "detected"\nkind = "responds"\ntrigger = "fault"\n'
                                     'condition = "TcuStatus.Stage >= 1"\nwithin_s = 0.05\n\n'
                                     '[[check]]\nname = "mu plausible"\nkind = "in_range"\nsignal = "TcuStatus.MuHat"\n'
                                     'lo = -0.05\nhi = 0.35\nduring = ["fault", 0.0, 0.2]\nvalid = "TcuStatus.ObserverValid"\n\n'
                                     '[[check]]\nname = "status each period"\nkind = "cycle_time"\nframe = "TcuStatus"\n'
                                     'nominal_s = 0.001\ntolerance_s = 0.0005\n\n'
                                     '[[check]]\nname = "observer lag"\nkind = "limit"\nkey = "observer_lag_ms"\nhi = 10.0\n'})
    result = _session(pytester)
    result.assert_outcomes(passed=20)
    logs = sorted((pytester.path / "hil-out").rglob("*.mcap"))
    assert len(logs) == 5, logs                                        # one run per scenario, 20 checks
    suite = load_checks(pytester.path / "test_s0.toml")                # the same 4 checks in every file
    for log in logs:
        t0 = time.perf_counter()
        results = judge(suite, Run.open(log))
        took = time.perf_counter() - t0
        print(f"{log.name}: {len(results)} checks judged in {took * 1e3:.0f} ms")
        assert len(results) == 4 and all(r.passed for r in results)   # the cost is printed, not asserted: a
        # timed assert fails on a busy host (1.107 s measured for one log in a full CI run; 63-192 ms alone)
