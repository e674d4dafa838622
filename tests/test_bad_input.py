"""Bad scenario input is one line and the right exit code, never a traceback: a real scenario file
mutated in many seeded random ways (keys deleted, values of the wrong type or absurd, junk bytes,
truncation, tables made scalars, deep nesting) goes through ``hil.config.load_scenario`` in process,
and a handful of the inputs an outside probe found go through the real ``hil run``."""
import math
import random
import re
import secrets
import subprocess
import time

import pytest

from hil.config import load_scenario, parse_scenario, parse_set
from hil.errors import EXIT_USAGE, HilError

from .conftest import SCENARIOS, hil_command, subprocess_env

#: the paper's scenario with every optional table filled in, so mutations reach them too
BASE = (SCENARIOS / "ffcc_a.toml").read_text() + """
[identifier]
observer_pole_rad_s = 500.0
baseline_samples = 50
settle_time_s = 0.008
window_samples = 6
max_corrections = 200
drill_particles = 64

[identifier.options.proposed]
particles = 200
noise_block = 8
init_std = [0.003, 0.02, 0.03]
projector = "clip"

[identifier.options.nlls]
window_samples = 7

[identifier.options.bayes]
particles = 100
peak_mu = [0.05, 0.25]

[bus]
heartbeat_period_s = 0.002
silence_periods = 25
lockstep_silence_s = 1.0
startup_timeout_s = 60

[reality.resistance]
factor = 1.2
"""

#: what a value may be replaced with: wrong types, extremes, non-finite, huge, negative, strings
VALUES = ['"text"', '""', "true", "false", "[1, 2]", "[]", "{ a = 1 }", "0", "-1", "-0.0", "1e-300", "-1e-300",
          "1e300", "-1e300", "nan", "inf", "-inf", "9223372036854775807", "-9223372036854775808", "1000000000",
          "1e9", "0.5", "2", '"\\u0000"', '"../../x"', "1979-05-27", "[[1], [2]]", '"' + "x" * 300 + '"']
#: bytes inserted at random places
JUNK = [b"\xff", b"\xfe\xff", b"\x00", b"\xc3", b"[", b"]", b"=", b'"', b"\n[run]\n", b"\n[[vehicle]]\n",
        b"[" * 2000, b"\x1b[2J", "é".encode(), b"\r", b"\\"]


def mutate(text: str, rng: random.Random) -> tuple[str, bytes]:
    """One mutation of ``text``: (what was done, the mutant's bytes)."""
    lines = text.splitlines(keepends=True)
    assignments = [i for i, line in enumerate(lines) if re.match(r"\s*[A-Za-z_\"]\S*\s*=", line)]
    headers = [i for i, line in enumerate(lines) if line.startswith("[")]
    kind = rng.choice(["delete", "value", "value", "value", "junk", "truncate", "table_scalar", "duplicate",
                       "nest", "rename"])
    if kind == "delete":
        i = rng.choice(assignments + headers)
        del lines[i]
        return f"delete line {i + 1}", "".join(lines).encode()
    if kind == "value":
        i = rng.choice(assignments)
        key = lines[i].split("=", 1)[0]
        value = rng.choice(VALUES)
        lines[i] = f"{key}= {value}\n"
        return f"line {i + 1}: {key.strip()} = {value[:40]}", "".join(lines).encode()
    if kind == "junk":
        data = text.encode()
        at = rng.randrange(len(data) + 1)
        junk = rng.choice(JUNK)
        return f"junk {junk[:10]!r} at byte {at}", data[:at] + junk + data[at:]
    if kind == "truncate":
        data = text.encode()
        at = rng.randrange(len(data))
        return f"truncated at byte {at}", data[:at]
    if kind == "table_scalar":
        i = rng.choice(headers)
        name = lines[i].strip().strip("[]").split(".")[0]
        body = "".join(line for line in lines if not line.startswith(f"[{name}"))
        return f"[{name}] made a scalar", f"{name} = {rng.choice(VALUES)}\n{body}".encode()
    if kind == "duplicate":
        i = rng.choice(assignments + headers)
        lines.insert(i, lines[i])
        return f"line {i + 1} twice", "".join(lines).encode()
    if kind == "nest":
        depth = rng.choice([10, 500, 5000, 100_000])
        return f"nesting {depth}", (f"deep = {'[' * depth}{']' * depth}\n" + text).encode()
    i = rng.choice(headers)
    lines[i] = lines[i].replace("[", "[x", 1)
    return f"table on line {i + 1} renamed", "".join(lines).encode()


def test_base_scenario_loads(tmp_path):
    path = tmp_path / "base.toml"
    path.write_text(BASE)
    s = load_scenario(path)
    assert s.identifier["options"]["proposed"]["particles"] == 200 and s.bus.silence_periods == 25


def test_mutated_scenarios_fail_in_one_line_or_load(tmp_path):
    """300 seeded mutants of a full scenario through load_scenario: each either loads or raises a
    HilError whose message is one line; never another exception."""
    seed = secrets.randbits(31)
    print(f"mutation seed {seed}")
    rng = random.Random(seed)
    path = tmp_path / "m.toml"
    outcomes = {"loaded": 0, "refused": 0}
    slowest = (0.0, "")
    for n in range(300):
        what, data = mutate(BASE, rng)
        path.write_bytes(data)
        t0 = time.perf_counter()
        try:
            s = load_scenario(path, parse_set(rng.choice([[], [], ["run.duration_s=0.9"], ["vehicle.gear_ratio=3"]])))
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
