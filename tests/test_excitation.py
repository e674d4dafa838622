"""The TCU's open-loop torque excitation (identifier/excitation.py): a function of the step since the
detected slip and of the seed only, the same in the TCU and in the bench's plant run."""

import numpy as np
import pytest

from identifier.excitation import Excitation

from .conftest import SCENARIOS, case_seed, hil


def test_the_sine_has_its_amplitude_frequency_and_duration_and_depends_on_the_seed_only():
    seed = case_seed()
    period_s = 1e-3
    ex = Excitation(amplitude_fraction=0.05, frequency_hz=50.0, duration_s=0.2)
    s = np.array([ex.shape(k, period_s, seed) for k in range(-5, 400)])
    assert np.all(s[:5] == 0.0) and np.all(s[5 + 200:] == 0.0)          # before the slip and after 0.2 s
    on = s[5:205]
    # a sampled sine with a random phase misses its crest by at most half a step: 1 - cos(pi f T)
    worst = 1.0 - np.cos(np.pi * 50.0 * period_s) + 1e-12
    assert 1.0 - worst <= on.max() <= 1.0 and -1.0 <= on.min() <= -1.0 + worst
    spectrum = np.abs(np.fft.rfft(on))
    assert np.fft.rfftfreq(on.size, period_s)[int(np.argmax(spectrum))] == pytest.approx(50.0, abs=5.0)
    again = np.array([ex.shape(k, period_s, seed) for k in range(-5, 400)])
    other = np.array([ex.shape(k, period_s, seed + 1) for k in range(-5, 400)])
    assert np.array_equal(s, again) and not np.array_equal(s, other)
    assert ex.command_nm(1000.0, 50, None, period_s, seed) == 1000.0              # no slip detected yet
    assert abs(ex.command_nm(1000.0, 50, 40, period_s, seed) - 1000.0) <= 50.0 + 1e-9


def test_prbs_is_plus_or_minus_one_held_for_half_a_period():
    seed = case_seed()
    ex = Excitation(amplitude_fraction=0.1, frequency_hz=100.0, duration_s=1.0, kind="prbs")
    s = np.array([ex.shape(k, 1e-3, seed) for k in range(1000)])
    assert set(np.unique(s)) <= {-1.0, 1.0}
    blocks = s.reshape(-1, 5)                                   # 1 / (2 f T) = 5 steps a sign
    assert np.all(blocks == blocks[:, :1])
    assert 0.3 < np.mean(blocks[:, 0] > 0) < 0.7


@pytest.mark.parametrize("table, words", [({"amplitude_fraction": 2.0}, "amplitude_fraction"),
                                          ({"kind": "chirp"}, "kind"), ({"frequency_hz": "fast"}, "frequency_hz"),
                                          ({"amplitude": 0.1}, "unknown")])
def test_a_bad_excitation_table_is_one_line_naming_the_field(tmp_path, table, words):
    text = (SCENARIOS / "ffcc_a.toml").read_text() + "\n[identifier.excitation]\n" + "".join(
        f"{k} = {v!r}\n".replace("'", '"') for k, v in table.items())
    path = tmp_path / "bad.toml"
    path.write_text(text)
    r = hil("run", path, "--bus", "inprocess", "--out", tmp_path)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert "[identifier.excitation]" in line and words in line


def test_the_tcu_commands_what_the_bench_plant_was_given():
    """The bench runs the plant with the TCU's detector and excitation; a TCU fed those readings
    commands exactly the same torques (so every strategy sees the same samples), with the
    excitation only after the detected slip start and for its duration."""
    from hil.benchmarks.identify import generate
    from hil.config import parse_scenario
    from identifier import TractionIdentifier

    seed = case_seed() % 1000 + 1
    overrides = {"identifier.excitation.amplitude_fraction": 0.05, "identifier.excitation.frequency_hz": 100.0,
                 "identifier.excitation.duration_s": 0.03, "run.duration_s": 1.3}
    sc = parse_scenario((SCENARIOS / "ffcc_a.toml").read_text(), "ffcc_a", overrides)
    data = generate(sc, seed)
    settings = sc.identifier_settings()
    ident = TractionIdentifier(settings, "nlls", seed)
    commands = np.array([ident.on_sensor(r).command.torque_nm for r in data.readings])
    applied = np.array(data.plant_torques_nm)
    np.testing.assert_array_equal(commands, applied)
    start = ident.detector.detected_step
    steps = np.array([r.step for r in data.readings])
    demand = settings.torque_demand_nm
    assert start is not None
    assert np.all(commands[steps <= start] == demand)
    on = commands[(steps > start) & (steps < start + 30)]
    assert np.max(np.abs(on / demand - 1.0)) == pytest.approx(0.05, rel=0.05)
    assert np.all(commands[steps >= start + 30] == demand)
