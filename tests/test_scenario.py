"""Scenario validation: one clear line naming the file and the field."""
import subprocess

import pytest

from hil.config import ScenarioError, load_scenario, parse_scenario

from .conftest import hil_command, subprocess_env


def test_paper_scenarios_load(ffcc_a_path, ffcc_b_path):
    a, b = load_scenario(ffcc_a_path), load_scenario(ffcc_b_path)
    assert a.run.mu_required == b.run.mu_required == 0.16
    assert tuple(a.fault_curve.params) == (-0.005, 0.585, -0.580, -0.525, -1.100)
    assert tuple(b.fault_curve.params) == (-0.002, 0.478, -0.476, -0.505, -1.180)
    assert a.vehicle.axle_load_kg == 13500 and a.vehicle.gear_ratio == 2.788


@pytest.mark.parametrize("edit, field", [
    (("[run]", "[run]\nbogus = 3"), "[run] bogus"),
    (("mu_required = 0.16", "mu_required = 1.5"), "[run] mu_required"),
    (("mu_required = 0.16", "mu_required = \"high\""), "[run] mu_required"),
    (("fault_time_s = 0.5\n", ""), "[run] fault_time_s"),
    (("exchange_period_s = 1e-3", "exchange_period_s = 1.5e-4"), "[run] exchange_period_s"),
    (("taus = [-0.525, -1.100]", "taus = [-0.525]"), "[curves.fault] taus"),
    (("wheel_radius_m = 0.4375", "wheel_radius_m = -1"), "[vehicle] wheel_radius_m"),
    (("motor_speed_noise_rad_s = 0.005", "motor_speed_noise_rad_s = -1"), "[sensors] motor_speed_noise_rad_s"),
])
def test_bad_fields_are_named(ffcc_a_path, edit, field):
    text = ffcc_a_path.read_text()
    old, new = edit
    assert old in text
    with pytest.raises(ScenarioError) as e:
        parse_scenario(text.replace(old, new, 1), "my.toml")
    msg = str(e.value)
    assert msg.startswith("my.toml: ") and field in msg and "\n" not in msg


def test_unknown_table_and_bad_toml(ffcc_a_path):
    with pytest.raises(ScenarioError, match=r"my.toml: extras: unknown key"):
        parse_scenario(ffcc_a_path.read_text() + "\n[extras]\nx = 1\n", "my.toml")
    with pytest.raises(ScenarioError, match=r"my.toml: not valid TOML"):
        parse_scenario("name = ", "my.toml")


def test_cli_reports_one_line_not_a_traceback(tmp_path, ffcc_a_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(ffcc_a_path.read_text().replace("duration_s = 1.0", "duration_s = 0.1"))
    r = subprocess.run(hil_command() + ["run", str(bad), "--out", str(tmp_path)], capture_output=True, text=True,
                       env=subprocess_env(), timeout=120)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().count("\n") == 0
    assert "bad.toml: [run] duration_s" in r.stderr
    assert not list(tmp_path.glob("*.mcap"))
