"""Issue 49's seven TCU variants end to end (scenarios/variants/variant_tcu.py: the docs' example TCU of
another make, python-can and cantools alone, with one fault each, on scenarios/variants/variants.dbc: a Motorola
signed torque, an offset signal, a value table): the pytest plugin runs the variant's own checks
(scenarios/variants/test_variants.toml) over a lockstep run, starting the variant with ``--hil-tcu-cmd``, and each
variant fails exactly its checks:

- on the local bus (the variant from this project's virtualenv: the bus is this package's python-can
  interface; three of them, one per path of the verdict), and
- on python-can's udp_multicast bus held to this machine, the variant run from a virtualenv with only
  python-can and cantools (tests/conftest.py's ``their_tcu`` makes it and checks ``import hil`` fails there).

A frozen and a crashed unit fail every check (the run fails as a whole: one judge); the crash's message gives
its exit code and its last stderr line.  Real processes, real buses, JUnit validated against junit-10.xsd."""
import os
import random
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET

import pytest

from .conftest import ROOT, subprocess_env

DATA = ROOT / "tests" / "data"
SUITES = ROOT / "scenarios" / "variants"
SUITE = SUITES / "test_variants.toml"
VARIANT = SUITES / "variant_tcu.py"
ALL = {"TIM-2", "ADH-1", "ADH-2", "ADH-3", "STG-1", "RNG-1", "SGN-1"}
#: what each variant must fail (variant_tcu.py's docstring says why)
FAILS = {"none": set(), "sign": {"SGN-1", "ADH-1", "ADH-2", "ADH-3"}, "saturate": {"ADH-3", "STG-1"},
         "stage0": {"STG-1"}, "range": {"RNG-1"}, "freeze": ALL, "crash": ALL}


def _verdicts(junit) -> tuple[dict, dict]:
    """({req: failure message} of the failed checks, {req: error message} of the errored ones) of a JUnit file,
    every case one of the suite's checks."""
    from lxml import etree

    schema = etree.XMLSchema(etree.parse(str(DATA / "junit-10.xsd")))
    assert schema.validate(etree.parse(str(junit))), schema.error_log
    cases = list(ET.parse(str(junit)).getroot().iter("testcase"))
    assert len(cases) == len(ALL), [c.get("name") for c in cases]
    failed, errored = {}, {}
    for c in cases:
        out = c.findtext("system-out") or ""
        req = next((line.split("[", 1)[1].split("]", 1)[0] for line in out.splitlines()
                    if line.startswith("FAIL [")), c.get("name"))
        if c.find("failure") is not None:
            failed[req] = c.find("failure").get("message") or ""
        if c.find("error") is not None:
            errored[c.get("name")] = c.find("error").get("message") or ""
    return failed, errored


#: the mode the matrix below runs in: lockstep in the suite (CI's time); ``HIL_VARIANTS_MODE=realtime`` runs the
#: same fourteen in real time (issue 49's measurement, docs/design/tcu-variants.md)
MODE = os.environ.get("HIL_VARIANTS_MODE", "lockstep")
#: in real time the variant runs at SCHED_FIFO 10 beside the plant (the suite's ``bus.rt_priority``), as
#: tests/test_mapping.py starts the faulty TCUs
CHRT = "chrt -f 10 " if MODE == "realtime" else ""


def _session(tmp_path, bus: str, tcu_cmd: str, mode: str = MODE):
    junit = tmp_path / "junit.xml"
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "hil.pytest_plugin", "-p", "no:cacheprovider", "-q",
                        str(SUITE), "--hil-bus", bus, "--hil-mode", mode, "--hil-tcu", "external",
                        "--hil-tcu-cmd", tcu_cmd,
                        "--hil-out", str(tmp_path / "out"), "--junitxml", str(junit)],
                       cwd=tmp_path, env=subprocess_env(), capture_output=True, text=True, timeout=600)
    return r, junit


def _check(r, junit, fault, mode: str = MODE):
    out = r.stdout[-4000:] + r.stderr[-2000:]
    failed, errored = _verdicts(junit)
    assert not errored, out
    props = {p.get("name"): p.get("value") for p in ET.parse(str(junit)).getroot().iter("property")}
    assert props["bus"].endswith(f" {mode}"), props          # the mode the session ran in
    named = {k for k in failed if k in ALL}
    if FAILS[fault] == ALL:            # the run failed as a whole: every check fails with the run's verdict
        assert len(failed) == len(ALL), out
        assert all("the TCU fell silent or died" in m for m in failed.values()), failed
    else:
        assert named == FAILS[fault], out
    if fault == "crash":
        assert all("exited with code 3" in m and "(a crash)" in m for m in failed.values()), failed
    if fault == "freeze":
        assert all("its process still runs" in m for m in failed.values()), failed
    print(f"{fault}: failed {sorted(named) if FAILS[fault] != ALL else 'every check (run failed)'}")


#: on the local bus, the variants that take each path of the verdict (a pass, checks failed, a process that dies),
#: all seven with ``HIL_VARIANTS_ALL=1``;
#: all seven run on udp_multicast below (all seven passed on both buses on 2026-11-28: 14 of 14, the note of stop 48)
LOCAL_BUS_FAULTS = tuple(FAILS) if os.environ.get("HIL_VARIANTS_ALL") else ("none", "sign", "crash")


@pytest.mark.slow
@pytest.mark.parametrize("fault", LOCAL_BUS_FAULTS)
def test_each_variant_fails_exactly_its_checks_on_the_local_bus(tmp_path, fault):
    bus = tempfile.mkdtemp(prefix="hil-bus-")
    try:
        r, junit = _session(tmp_path, f"localbus:{bus}",
                            f"{CHRT}{sys.executable} {VARIANT} --bus {{bus}} --fault {fault}")
    finally:
        shutil.rmtree(bus, ignore_errors=True)
    _check(r, junit, fault)


@pytest.mark.slow
@pytest.mark.parametrize("fault", list(FAILS))
def test_each_variant_fails_exactly_its_checks_with_python_can_alone(tmp_path, their_tcu, fault):
    py, home = their_tcu
    mine = tmp_path / "tcu"                   # the variant and its DBC beside the example, in a directory of its own
    mine.mkdir()
    for f in (home / "python_can_tcu.py", VARIANT, SUITES / "variants.dbc"):
        shutil.copy(f, mine)
    seed = int.from_bytes(os.urandom(4), "little")
    rng = random.Random(seed)
    bus = f"udp_multicast:239.255.{rng.randrange(1, 255)}.{rng.randrange(1, 255)}:{rng.randrange(40000, 60000)}"
    print(f"bus {bus} (drawn, seed {seed})")
    r, junit = _session(tmp_path, bus, f"{CHRT}{py} {mine / 'variant_tcu.py'} --dbc {mine / 'variants.dbc'} --bus {{bus}} "
                                       f"--fault {fault}")
    _check(r, junit, fault)


@pytest.mark.realtime
def test_a_variant_with_python_can_alone_fails_exactly_its_checks_in_real_time(tmp_path, their_tcu):
    """The sign-error variant from the python-can-only virtualenv on udp_multicast, in real time (SCHED_FIFO 10
    for it and the plant): it fails exactly SGN-1 and the adhesion checks, none errors.  All fourteen of the
    matrix above ran so on 2026-11-29 (``HIL_VARIANTS_MODE=realtime``, docs/design/verdicts.md); CI keeps this
    one.  A run whose only extra failure is the cycle-time check (TIM-2) is made again, three runs in all, as
    tests/test_mapping.py's real-time suite does: a CPU taken away on a shared machine is not the unit's."""
    if os.geteuid() != 0 and os.environ.get("CI") != "true":
        pytest.skip("SCHED_FIFO (chrt -f 10) needs root here")
    py, home = their_tcu
    mine = tmp_path / "tcu"
    mine.mkdir()
    for f in (home / "python_can_tcu.py", VARIANT, SUITES / "variants.dbc"):
        shutil.copy(f, mine)
    seed = int.from_bytes(os.urandom(4), "little")
    rng = random.Random(seed)
    for attempt in range(1, 4):
        bus = f"udp_multicast:239.255.{rng.randrange(1, 255)}.{rng.randrange(1, 255)}:{rng.randrange(40000, 60000)}"
        print(f"run {attempt}: bus {bus} (drawn, seed {seed})")
        run = tmp_path / f"run{attempt}"
        run.mkdir()
        r, junit = _session(run, bus, f"chrt -f 10 {py} {mine / 'variant_tcu.py'} --dbc {mine / 'variants.dbc'} "
                                      f"--bus {{bus}} --fault sign", mode="realtime")
        failed, errored = _verdicts(junit)
        if errored or set(failed) - FAILS["sign"] != {"TIM-2"} or attempt == 3:
            break
        print(f"run {attempt}: TIM-2 failed beside the expected checks ({failed['TIM-2']}); once more")
    _check(r, junit, "sign", mode="realtime")
