"""A TCU of another make with python-can and cantools and nothing of this project joins a run (issue 49,
item 2): the docs' example TCU (docs/examples/python_can_tcu.py), copied with its DBC into a directory of
its own and run from a virtualenv made here with only ``python-can[multicast]`` and ``cantools`` from the
package registry (``import hil`` fails there), on python-can's udp_multicast bus held to this machine, in
lockstep: through the pytest plugin (it passes the example suite's four checks) and through ``hil run
--tcu external`` and ``hil check`` (with its creep set-point raised out of reach it slips: the two adhesion
checks fail, the two timing checks pass).  Real processes, a real bus; under CI=true it never skips."""
import json
import subprocess
import sys
import tomllib
import xml.etree.ElementTree as ET


from hil.bus.multicast import new_group

from .conftest import SCENARIOS, bare_env, hil, subprocess_env

SUITE = SCENARIOS / "suites" / "test_their_tcu.toml"
CHECKS = {"TIM-1", "TIM-2", "ADH-1", "ADH-2"}

def tcu_argv(their_tcu, bus, *extra) -> list[str]:
    py, home = their_tcu
    return [str(py), str(home / "python_can_tcu.py"), "--dbc", str(home / "their.dbc"), "--bus", bus, *extra]


def test_a_tcu_with_python_can_alone_passes_the_example_suite_through_the_plugin(their_tcu, tmp_path):
    """``pytest -p hil.pytest_plugin`` on the example suite, ``--hil-bus udp_multicast:GROUP:PORT``, the
    plugin starting the TCU (``env -u PYTHONPATH``: the plugin's environment names this tree) for the run:
    four checks, four passes, none skipped; the JUnit names the bus."""
    bus = "udp_multicast:{}:{}".format(*new_group())
    junit = tmp_path / "junit.xml"
    cmd = "env -u PYTHONPATH " + " ".join(tcu_argv(their_tcu, "{bus}"))
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "-q",
                        str(SUITE), "--hil-bus", bus, "--hil-tcu", "external", "--hil-tcu-cmd", cmd,
                        "--hil-out", str(tmp_path / "out"), "--junitxml", str(junit)],
                       cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=600)
    out = r.stdout[-4000:] + r.stderr[-2000:]
    root = ET.parse(str(junit)).getroot()
    cases = list(root.iter("testcase"))
    assert len(cases) == 4, out
    bad = [(c.get("name"), [e.tag for e in c]) for c in cases if any(e.tag in ("failure", "error", "skipped") for e in c)]
    assert not bad and r.returncode == 0, out
    props = [(p.get("name"), p.get("value")) for p in root.iter("property")]
    assert ("bus", f"{bus} lockstep") in props and ("dbc", "their.dbc") in props, props
    print(r.stdout.strip().splitlines()[-1])


def test_hil_run_with_the_tcu_external_and_hil_check_judge_its_slip(their_tcu, tmp_path):
    """The TCU started by hand, ``hil run --tcu external`` on the suite's scenario and overrides, then
    ``hil check`` on the log: with the creep set-point at 50 km/h (never reached: the demand passes through
    the wet patch) the wheel slips, so ADH-1 and ADH-2 fail and TIM-1 and TIM-2 pass; the run's summary
    names the bus and holds no suspicious or rejected frame."""
    suite = tomllib.loads(SUITE.read_text())
    sets = [a for k, v in suite["set"].items() for a in ("--set", f"{k}={json.dumps(v)}")]
    bus = "udp_multicast:{}:{}".format(*new_group())
    log = tmp_path / "tcu.log"
    with open(log, "w") as err:
        tcu = subprocess.Popen(tcu_argv(their_tcu, bus, "--set-point-kmh", "50"), cwd=their_tcu[1], env=bare_env(),
                               stdin=subprocess.DEVNULL, stdout=err, stderr=err, start_new_session=True)
    try:
        r = hil("run", SUITE.parent / suite["scenario"], "--bus", bus, "--tcu", "external", "--out", tmp_path,
                "--no-rrd", "--json", *sets, timeout=600, cwd=tmp_path)
    finally:
        tcu.terminate()
        try:
            tcu.wait(10)
        except subprocess.TimeoutExpired:
            tcu.kill()
            tcu.wait()
    assert r.returncode == 0, r.stderr + log.read_text()[-2000:]
    s = json.loads(r.stdout)
    assert (s["bus"], s["mode"], s["transport"], s["frame_auth"]) == (bus, "lockstep", "external", "off"), s
    assert s["suspicious"] == {} and s["rejected_frames"] == {}, s
    assert f"warning: bus {bus}: any process of any user on this machine can join it" in r.stderr, r.stderr
    c = hil("check", s["mcap"], SUITE, timeout=300, cwd=tmp_path)
    verdicts = {line.split("[", 1)[1].split("]", 1)[0]: line.split(" ", 1)[0]
                for line in c.stdout.splitlines() if line.startswith(("PASS [", "FAIL ["))}
    assert verdicts == {"TIM-1": "PASS", "TIM-2": "PASS", "ADH-1": "FAIL", "ADH-2": "FAIL"}, c.stdout + c.stderr
    assert c.returncode != 0, c.stdout
    print(f"slipping TCU: {verdicts}; macro-slip {s['macro_slip_s']:.3f} s, "
          f"adhesion used on the wet patch {s['adhesion_utilisation_low']:.3f}")
