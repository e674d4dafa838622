"""Fault-curve families (plant/families.py) and Polach's law as the plant's friction law (plant/friction.py).

The Polach plant is checked against the law written again here from Polach (Wear 2005) with ``math``;
every family's draws are parsed as scenarios and run on the real plant, which must reach the serious
stage inside the T_det band the draw was made for.  Seeds of generated cases are drawn at test time and
printed: a failure names the seed that reproduces it.
"""
import json
import math

import numpy as np
import pytest

from hil.config import ScenarioError, parse_scenario
from plant import PolachCurve, WheelsetPlant, families
from plant.families import FAMILIES, Base, describe, draw, draw_rng, draw_scenario_text, sample_curves

from .conftest import SCENARIOS, case_seed, hil

BASE_TEXT = (SCENARIOS / "ffcc_a.toml").read_text()
FFCC_A_FAULT = """[curves.fault]               # FFCC-a, paper Table 2 (v_s in km/h)
lambda0 = -0.005
lambdas = [0.585, -0.580]
taus = [-0.525, -1.100]
"""
POLACH_FAULT = """[curves.fault]
model = "polach"
mu_static = 0.2
A = 0.4
B_s_per_m = 1.5
k_A = 0.6
k_S = 0.4
stiffness = 40.0
"""


def fresh_seed(what: str) -> int:
    return case_seed(what)


def polach_scenario_text(fault_table: str = POLACH_FAULT) -> str:
    assert FFCC_A_FAULT in BASE_TEXT
    return BASE_TEXT.replace(FFCC_A_FAULT, fault_table)


def polach_by_hand(v_s_kmh, v_t_ms, mu_static, A, B, k_A, k_S, stiffness) -> float:
    """Polach 2005, longitudinal creep only, written again: f = mu0 ((1 - A) e^(-B w) + A), s = w / V,
    eps = stiffness s / f, mu = 2 f / pi (k_A eps / (1 + (k_A eps)^2) + atan(k_S eps)); odd in v_s."""
    w = abs(v_s_kmh) / 3.6
    if w == 0.0:
        return 0.0
    f = mu_static * ((1.0 - A) * math.exp(-B * w) + A)
    eps = stiffness * (w / v_t_ms) / f
    mu = 2.0 * f / math.pi * (k_A * eps / (1.0 + (k_A * eps) ** 2) + math.atan(k_S * eps))
    return math.copysign(mu, v_s_kmh)


# -- Polach's law in the plant ------------------------------------------------------------------------------
def test_polach_plant_matches_the_law_written_again():
    sc = parse_scenario(polach_scenario_text(), "polach.toml")
    curve = sc.fault_curve
    assert isinstance(curve, PolachCurve) and not hasattr(curve, "params")
    law = (0.2, 0.4, 1.5, 0.6, 0.4, 40.0)
    plant = WheelsetPlant(sc.plant_config())
    torque = plant.equilibrium_torque_nm
    fault_step = round(sc.run.fault_time_s / sc.run.exchange_period_s)
    checked = braking = 0
    speed_matters = 0.0
    for k in range(fault_step + 160):
        # 120 periods of slip under the held torque, then a reversed torque drives the creep negative
        s = plant.step(torque if k < fault_step + 120 else -3 * torque)
        if k + 1 == fault_step:
            # the truth's train speed is the one at the fault (plant.model.train_speed_before_fault)
            assert curve.reference_train_speed_ms == pytest.approx(s.train_speed_ms, abs=1e-6)
        if not s.fault_active:
            continue
        expected = polach_by_hand(s.creep_speed_kmh, s.train_speed_ms, *law)
        assert s.mu == pytest.approx(expected, rel=1e-12, abs=1e-15), (s.t_s, s.creep_speed_kmh)
        checked += 1
        braking += s.creep_speed_kmh < -0.05
        speed_matters = max(speed_matters, abs(expected - polach_by_hand(s.creep_speed_kmh, 10.0, *law)))
    assert checked >= 160 and braking >= 5, (checked, braking)
    # the plant's mu follows the integrated train speed, not a fixed one: the check above can tell
    assert speed_matters > 1e-4
    # the numpy truth is the same law at the reference train speed, odd in the creep speed
    for v in (-2.0, -0.3, 0.0, 0.05, 0.4, 1.3, 2.7, 8.0, 25.0):
        assert float(curve.mu(v)) == pytest.approx(polach_by_hand(v, curve.reference_train_speed_ms, *law),
                                                   rel=1e-13, abs=1e-16)
    # the law slips: the serious stage is reached, past the peak of the truth
    v_peak, mu_peak = curve.peak()
    assert 0 < v_peak < 29 and mu_peak < sc.run.mu_required


def test_polach_curve_at_another_train_speed_is_the_same_curve_of_creep_speed():
    c = PolachCurve(0.3, 0.3, 0.8, 0.7, 0.5, 60.0, 10.0)
    d = c.at_train_speed(12.5)
    v = np.linspace(0, 10, 101)
    np.testing.assert_allclose(d.mu(v), c.mu(v), rtol=1e-13, atol=0)
    assert d.stiffness == pytest.approx(75.0) and d.reference_train_speed_ms == 12.5
    # but at a fixed stiffness a faster train has a smaller creepage, so less adhesion at the same creep
    assert float(c.mu_at(0.5, 12.5)) < float(c.mu(0.5))


# -- scenario checks -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("edits, field", [
    ([("stiffness = 40.0", "stiffness = 40.0\nlambda0 = 0.0")], "[curves.fault] lambda0"),
    ([("stiffness = 40.0\n", "")], "[curves.fault] stiffness"),
    ([("A = 0.4", "A = 0.0")], "[curves.fault] A"),
    ([("A = 0.4", "A = 1.5")], "[curves.fault] A"),
    ([("k_S = 0.4", "k_S = 0.7")], "[curves.fault] k_S"),
    ([("k_A = 0.6", "k_A = 1.2")], "[curves.fault] k_A"),
    ([("B_s_per_m = 1.5", "B_s_per_m = -1.0")], "[curves.fault] B_s_per_m"),
    ([("mu_static = 0.2", "mu_static = \"high\"")], "[curves.fault] mu_static"),
    ([("stiffness = 40.0", "stiffness = 40.0\nreference_train_speed_ms = -3.0")],
     "[curves.fault] reference_train_speed_ms"),
    ([('model = "polach"', 'model = "bogus"')], "[curves.fault] model"),
    ([('model = "polach"', "model = 3")], "[curves.fault] model"),
    ([("[curves.normal]", "[curves.normal]\nmodel = \"polach\"")], "[curves.normal] model"),
    # no friction decrease (B = 0, A = 1): mu only rises, so no peak inside 0-29 km/h
    ([("B_s_per_m = 1.5", "B_s_per_m = 0.0"), ("A = 0.4", "A = 1.0")], "[curves.fault]: must rise to a positive peak"),
])
def test_bad_polach_tables_are_one_line_naming_the_field(edits, field):
    text = polach_scenario_text()
    for old, new in edits:
        assert old in text
        text = text.replace(old, new, 1)
    with pytest.raises(ScenarioError) as e:
        parse_scenario(text, "my.toml")
    msg = str(e.value)
    assert msg.startswith("my.toml: ") and field in msg and "\n" not in msg, msg


def test_exp_is_the_default_model_and_may_be_named():
    a = parse_scenario(BASE_TEXT, "a.toml")
    b = parse_scenario(BASE_TEXT.replace("lambda0 = -0.005", 'model = "exp"\nlambda0 = -0.005'), "b.toml")
    assert a.fault_curve == b.fault_curve and a.fault_curve.model == "exp"


def test_fmu_export_refuses_a_polach_curve_in_one_line(tmp_path):
    path = tmp_path / "polach.toml"
    path.write_text(polach_scenario_text())
    out = tmp_path / "plant.fmu"
    r = hil("fmu", "export", path, "-o", out, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr
    assert "model = 'polach' cannot be exported" in r.stderr and "exponential" in r.stderr
    assert not out.exists() and not list(tmp_path.glob("*.partial"))


# -- families --------------------------------------------------------------------------------------------------
def test_family_names_and_specs():
    assert set(FAMILIES) == {"exp", "polach", "default"}
    for f in FAMILIES:
        spec = describe(f)
        assert json.loads(json.dumps(spec)) == spec
        assert spec["peak_mu"]["range"] == [0.05, 0.25] and spec["peak_creep_kmh"]["range"] == [0.4, 3.0]
        assert spec["t_det_target_s"]["range"] == [0.02, 0.15]
    assert describe("default")["laws"] == ["exp", "polach"]
    with pytest.raises(ValueError, match="unknown family"):
        draw("bogus", 1, 0)


def test_a_draw_is_reproducible_and_indices_differ():
    seed = fresh_seed("reproducibility")
    for family in FAMILIES:
        a, b = draw(family, seed, 3), draw(family, seed, 3)
        assert a == b
        assert draw_scenario_text(BASE_TEXT, family, seed, 3) == draw_scenario_text(BASE_TEXT, family, seed, 3)
        c = draw(family, seed, 4)
        assert c.curve != a.curve and c.mu_required != a.mu_required and c.t_det_target_s != a.t_det_target_s
    assert draw("exp", seed, 3).curve != draw("polach", seed, 3).curve


def test_sample_curves_is_draws_prior():
    """``sample_curves`` on a draw's own stream gives the draw's curve; a big batch has the documented
    distribution (ranges, the joint rule, uniform / log-uniform where the rule does not cut, the coin)."""
    seed = fresh_seed("sample_curves")
    base = families.DEFAULT_BASE
    for family in FAMILIES:
        for index in range(3):
            d = draw(family, seed, index)
            batch = sample_curves(family, 1, draw_rng(family, seed, index), base.initial_train_speed_ms)
            curve = batch.curve(0)
            if isinstance(curve, PolachCurve):
                curve = curve.at_train_speed(d.curve.reference_train_speed_ms)
            assert curve == d.curve and batch.peak_mu[0] == d.peak_mu and batch.peak_creep_kmh[0] == d.peak_creep_kmh
            grid = np.linspace(0, 5, 11)
            np.testing.assert_allclose(batch.mu(grid)[0], d.curve.mu(grid), rtol=1e-12, atol=1e-15)
    from scipy.stats import kstest

    rng = np.random.default_rng(seed)
    for family in FAMILIES:
        b = sample_curves(family, 40_000, rng, 10.4)
        mp, vp = b.peak_mu, b.peak_creep_kmh
        assert mp.min() >= 0.05 and mp.max() <= 0.25 and vp.min() >= 0.4 and vp.max() <= 3.0
        assert np.all(mp <= families.peak_mu_cap(vp))
        free = vp > 1.0                       # the joint rule cuts nothing here (cap > 0.25)
        assert kstest((mp[free] - 0.05) / 0.2, "uniform").pvalue > 1e-6
        assert kstest(np.log(vp[free] / 1.0) / np.log(3.0), "uniform").pvalue > 1e-6
        polach = np.mean(b.law == families.LAW_POLACH)
        expected = {"exp": 0.0, "polach": 1.0, "default": 0.5}[family]
        assert abs(polach - expected) < 5 * math.sqrt(0.25 / 40_000) + 1e-12
        if family != "polach":
            mu0 = b.mu0[b.law == families.LAW_EXP]
            assert kstest(mu0 / 0.02, "uniform").pvalue > 1e-6
        # rows evaluate as their curve objects
        grid = np.linspace(0, 6, 25)
        rows = b.mu(grid)
        for i in range(0, 40_000, 4001):
            np.testing.assert_allclose(rows[i], b.curve(i).mu(grid), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("family", ["exp", "polach"])
def test_family_curves_peak_where_they_claim(family):
    """Every curve rises monotonically to its drawn peak and the peak is the curve's maximum (FrictionCurve.peak /
    PolachCurve.peak find it); mu(0) is the drawn one."""
    seed = fresh_seed(f"{family} peaks")
    b = sample_curves(family, 300, np.random.default_rng(seed), 10.4)
    grid_rise = np.linspace(0, 1, 201)
    for i in range(len(b)):
        c = b.curve(i)
        v_peak, mu_peak = c.peak()
        assert v_peak == pytest.approx(b.peak_creep_kmh[i], rel=1e-4), i
        assert mu_peak == pytest.approx(b.peak_mu[i], rel=1e-9), i
        assert float(c.mu(0.0)) == pytest.approx(b.mu0[i], abs=1e-12)
        rise = c.mu(grid_rise * b.peak_creep_kmh[i])
        assert np.all(np.diff(rise) > 0), i
        wide = c.mu(np.linspace(b.peak_creep_kmh[i], 30.0, 3000))
        assert wide.max() <= b.peak_mu[i] * (1 + 1e-12), i
        if family == "exp":
            # the exponential form falls monotonically after its peak
            assert np.all(np.diff(wide) <= 1e-15), i
            assert np.all(np.abs(c.params[1:3]) <= 5) and np.all((c.params[3:] >= -10) & (c.params[3:] <= -1e-3))


def run_until_serious(sc, seed=1):
    """The plant with the scenario's torque demand, as ``hil bench identify`` generates its data (PlantRig)."""
    from identifier import TorqueCommand
    from hil.plant_node import PlantRig
    from hil.trace import Trace

    trace = Trace(sc)
    rig = PlantRig(sc, seed, trace)
    torque = sc.identifier_settings().torque_demand_nm
    limit = round((sc.run.fault_time_s + 0.25) / sc.run.exchange_period_s)
    for _ in range(limit):
        r = rig.sense()
        if trace.tracker.serious_time_s is not None:
            break
        rig.apply(TorqueCommand(r.step, torque))
    return trace.tracker


@pytest.mark.parametrize("family, draws", [("exp", 6), ("polach", 6), ("default", 4)])
def test_draws_parse_and_slip_within_the_band(family, draws):
    seed = fresh_seed(f"{family} draws")
    base = Base.from_text(BASE_TEXT)
    assert base == families.DEFAULT_BASE          # ffcc_a's, as documented
    figures = []
    for index in range(draws):
        text = draw_scenario_text(BASE_TEXT, family, seed, index)
        sc = parse_scenario(text, f"{family}-{seed}-{index}.toml")
        d = draw(family, seed, index, base)
        assert sc.name == d.name == f"{family}-{seed}-{index}"
        assert sc.run.mu_required == d.mu_required and sc.fault_curve == d.curve
        assert (d.law == "polach") == isinstance(sc.fault_curve, PolachCurve)
        # everything else is the base's
        ref = parse_scenario(BASE_TEXT, "ffcc_a.toml")
        assert (sc.vehicle, sc.normal_curve, sc.sensors, sc.bus) == \
            (ref.vehicle, ref.normal_curve, ref.sensors, ref.bus)
        assert sc.run.fault_time_s == ref.run.fault_time_s and sc.run.duration_s == ref.run.duration_s
        v_peak, mu_peak = sc.fault_curve.peak()
        assert v_peak == pytest.approx(d.peak_creep_kmh, rel=1e-4) and mu_peak == pytest.approx(d.peak_mu, rel=1e-9)
        assert d.peak_mu < d.mu_required
        assert 0.02 <= d.t_det_target_s <= 0.15 and d.t_det_predicted_s == pytest.approx(d.t_det_target_s, rel=2e-3)
        tracker = run_until_serious(sc)
        t_det = tracker.deterioration_time_s
        figures.append(f"{index}: {d.law} pred {d.t_det_predicted_s * 1e3:.1f} sim {t_det * 1e3:.1f} ms")
        assert 0.015 <= t_det <= 0.170, figures[-1]
        # the plant's tracker sees the crossing at the first exchange period after it; the prediction
        # (RK4 at 0.25 ms from the ideal state) differs from the plant's crossing (0.1 ms steps, a held creep
        # that drifts) by tens of microseconds on slow approaches: -28.5 us was seen (HIL_TEST_SEED=1587076047),
        # 300 draws gave -1.8..+997 us, so one prediction step is allowed either side
        tol = families.PREDICT_STEP_S
        assert d.t_det_predicted_s - tol <= t_det <= d.t_det_predicted_s + sc.run.exchange_period_s + tol, figures[-1]
        assert abs(d.t_det_predicted_s - t_det) <= 0.1 * t_det
    print("; ".join(figures))


def test_draw_scenario_text_keeps_the_other_tables():
    seed = fresh_seed("other tables")
    base_text = BASE_TEXT + '\n[bus]\nheartbeat_period_s = 0.003\n\n[identifier]\nsettle_time_s = 0.004\n'
    ref = parse_scenario(base_text, "base.toml")
    sc = parse_scenario(draw_scenario_text(base_text, "default", seed, 0), "drawn.toml")
    assert sc.bus == ref.bus and sc.identifier == ref.identifier and sc.bus.heartbeat_period_s == 0.003
    assert sc.identifier_settings().settle_time_s == 0.004


@pytest.mark.parametrize("family", ["exp", "polach"])
def test_every_draw_slips_and_its_target_is_reachable(family):
    """mu_required lies above the fault's peak (the wheelset slips) and its predicted T_det meets the
    target, for curves whose slowest T_det is under the 150 ms band's top too (a Polach curve peaking at
    0.45 km/h reaches its peak creep within 141 ms even from mu_required just above its peak: CI drew
    polach seed 10229388 draw 4, mu_required came out equal to the peak; that draw is checked too)."""
    seed = fresh_seed(f"{family} targets")
    draws = [(seed, i) for i in range(20)] + ([(10229388, 4)] if family == "polach" else [])
    for s, i in draws:
        d = draw(family, s, i)
        assert d.mu_required > d.peak_mu, (s, i)
        assert d.t_det_predicted_s == pytest.approx(d.t_det_target_s, rel=2e-3), (s, i)
        assert families.TDET_S[0] * 0.99 <= d.t_det_target_s <= families.TDET_S[1], (s, i)
