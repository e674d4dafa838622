"""Bad scenario input is one line and the right exit code, never a traceback: a real scenario file
mutated in many seeded random ways (keys deleted, values of the wrong type or absurd, junk bytes,
truncation, tables made scalars, deep nesting) goes through ``hil.config.load_scenario`` in process,
and a handful of the inputs an outside probe found go through the real ``hil run``."""
import math
import random
import re
import subprocess
import time

import pytest

from hil.testing import SET_CHOICES, full_scenario_text, mutate
from hil.config import load_scenario, parse_scenario, parse_set
from hil.errors import EXIT_USAGE, HilError

from .conftest import SCENARIOS, case_seed, hil_command, subprocess_env

#: the paper's scenario with every optional table filled in, so mutations reach them too; the mutator
#: is the library's (``hil bench robustness`` uses the same one)
BASE = full_scenario_text()


def test_base_scenario_loads(tmp_path):
    path = tmp_path / "base.toml"
    path.write_text(BASE)
    s = load_scenario(path)
    assert s.identifier["options"]["proposed"]["particles"] == 200 and s.bus.silence_periods == 25


def test_mutated_scenarios_fail_in_one_line_or_load(tmp_path):
    """300 seeded mutants of a full scenario through load_scenario: each either loads or raises a
    HilError whose message is one line; never another exception."""
    seed = case_seed("mutation")
    rng = random.Random(seed)
    path = tmp_path / "m.toml"
    outcomes = {"loaded": 0, "refused": 0}
    slowest = (0.0, "")
    for n in range(300):
        what, data = mutate(BASE, rng)
        path.write_bytes(data)
        t0 = time.perf_counter()
        try:
            s = load_scenario(path, parse_set(list(rng.choice(SET_CHOICES))))
        except HilError as e:
            msg = str(e)
            assert msg and "\n" not in msg and "\r" not in msg and len(msg) < 600, (seed, n, what, msg)
            assert msg.startswith(str(path)) or msg.startswith("--set"), (seed, n, what, msg)
            outcomes["refused"] += 1
        except Exception as e:  # noqa: BLE001 - the point of the test
            pytest.fail(f"seed {seed} mutant {n} ({what}): {type(e).__name__}: {e}")
        else:
            outcomes["loaded"] += 1
            assert s.steps >= 1 and math.isfinite(s.run.duration_s)
        slowest = max(slowest, (time.perf_counter() - t0, what))
    print(outcomes, f"slowest {slowest[0]:.2f} s ({slowest[1]})")
    assert outcomes["refused"] >= 150 and slowest[0] < 10, (outcomes, slowest)


@pytest.mark.parametrize("edit, says", [
    (("gear_ratio = 2.788", "gear_ratio = 1e-300"), "[vehicle] gear_ratio: must be in [0.05, 100], got 1e-300"),
    (("[run]", "[identifier]\nbaseline_samples = 0\n[run]"), "[identifier] baseline_samples: must be in [2, 1e+06]"),
    (("[run]", "[identifier.options.proposed]\nparticles = 1e9\n[run]"),
     "[identifier.options.proposed] particles: must be in [0, 1e+06], got 1000000000.0"),
    (("[run]", "[identifier.options.nlls]\nbogus = 1\n[run]"),
     "[identifier.options.nlls] bogus: unknown option (known: c_lw, c_up, k_pe, window_samples)"),
    (("integration_step_s = 1e-4", "integration_step_s = 1e-300"), "integration steps; more than 1e+08 are refused"),
    (("[vehicle]", "curves = [1]\n[vehicle]"), "[curves]: must be a table holding"),
    (("motor_speed_noise_rad_s = 0.005", "motor_speed_noise_rad_s = 500.0"),
     "leave the PlantSensor frame's range +-2000"),
])
def test_absurd_values_are_named(edit, says):
    text = (SCENARIOS / "ffcc_a.toml").read_text()
    old, new = edit
    assert old in text
    if old == "[vehicle]":          # curves = [1] replaces the curve tables
        text = re.sub(r"\[curves\.normal\].*?(?=\[run\])", "", text, flags=re.S)
    with pytest.raises(HilError) as e:
        parse_scenario(text.replace(old, new, 1), "my.toml")
    assert says in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_scalar_where_set_wants_a_table():
    text = re.sub(r"\[run\].*?(?=\[sensors\])", "", (SCENARIOS / "ffcc_a.toml").read_text(), flags=re.S)
    with pytest.raises(HilError, match=r"--set run.duration_s: run is not a table in my.toml"):
        parse_scenario(text.replace('name = "ffcc_a"', 'name = "ffcc_a"\nrun = 5'), "my.toml",
                       parse_set(["run.duration_s=3"]))


def _cli_cases(tmp_path):
    text = (SCENARIOS / "ffcc_a.toml").read_text()
    (tmp_path / "utf8.toml").write_bytes(text.encode() + b"\n# \xff\xfe\n")
    (tmp_path / "deep.toml").write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n" + text)
    (tmp_path / "gear.toml").write_text(text.replace("gear_ratio = 2.788", "gear_ratio = 1e-300"))
    (tmp_path / "particles.toml").write_text(text + "\n[identifier.options.proposed]\nparticles = 1e9\n")
    (tmp_path / "run5.toml").write_text(re.sub(r"\[run\].*?(?=\[sensors\])", "", text, flags=re.S)
                                        .replace('name = "ffcc_a"', 'name = "ffcc_a"\nrun = 5'))
    (tmp_path / "adir.toml").mkdir()
    return [("utf8.toml", [], "not UTF-8 text (byte"), ("deep.toml", [], "nested too deep"),
            ("gear.toml", [], "[vehicle] gear_ratio"), ("particles.toml", [], "particles: must be in [0, 1e+06]"),
            ("run5.toml", ["--set", "run.duration_s=3"], "run is not a table"),
            ("adir.toml", [], "is a directory, not a scenario file")]


def test_bad_scenarios_via_the_cli_are_one_line_and_exit_2(tmp_path):
    for name, extra, says in _cli_cases(tmp_path):
        r = subprocess.run(hil_command() + ["run", str(tmp_path / name), "--bus", "inprocess", "--out",
                                            str(tmp_path / "out"), *extra],
                           capture_output=True, text=True, env=subprocess_env(), timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == EXIT_USAGE and len(lines) == 1 and says in lines[0], (name, r.stderr)
        assert lines[0].startswith("hil run: error: ")
    assert not (tmp_path / "out").exists()


def test_a_value_that_makes_the_plant_diverge_is_one_line_and_exit_2(tmp_path):
    """Found by ``hil bench robustness`` (scenarios part, seed 1477779603, cases 203 and 300): a scenario
    that loads but whose physics diverge at once (``[reality.resistance] factor = 1e300``) ended ``hil run``
    with a FloatingPointError traceback (exit 1)."""
    path = tmp_path / "diverge.toml"
    path.write_text((SCENARIOS / "ffcc_a.toml").read_text() + "\n[reality.resistance]\nfactor = 1e300\n")
    load_scenario(path)                                   # it loads: the value is finite and >= 0
    for bus in ("inprocess", "local"):
        r = subprocess.run(hil_command() + ["run", str(path), "--bus", bus, "--out", str(tmp_path / "out"),
                                            "--no-rrd"], capture_output=True, text=True, env=subprocess_env(),
                           timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == EXIT_USAGE and "Traceback" not in r.stderr, (bus, r.stderr)
        assert lines[-1].startswith("hil run: error: ") and "diverged" in lines[-1], (bus, r.stderr)
