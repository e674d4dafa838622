"""The reality emulator: each effect does what its physics says, and only when switched on."""
import json
import math
import subprocess

import numpy as np
import pytest

from hil.log.read import read_log
from hil.exchange import run
from hil.effects import TRUTH_KEY, CanReality, with_reality
from hil.config import load_scenario
from identifier import SensorReading
from plant import SensorConfig, SensorModel, WheelsetPlant
from hil.effects import parse_effect
from plant.reality import RealityPlant, RealitySensors

from .conftest import hil_command, subprocess_env


@pytest.fixture(scope="module")
def scenario():
    from .conftest import SCENARIOS
    return load_scenario(SCENARIOS / "ffcc_a.toml")


def trajectory(plant, torque, steps):
    return np.array([[s.motor_speed_rad_s, s.train_speed_ms, s.creep_speed_kmh, s.mu, s.load_torque_nm]
                     for s in (plant.step(torque) for _ in range(steps))])


def test_no_effect_is_the_nominal_plant(scenario):
    cfg = scenario.plant_config()
    nom, real = WheelsetPlant(cfg), RealityPlant(cfg, {})
    a = trajectory(nom, nom.equilibrium_torque_nm, 700)
    b = trajectory(real, real.equilibrium_torque_nm, 700)
    assert np.allclose(a, b, rtol=0, atol=1e-9)


def test_load_transfer_normal_force_matches_hand_formula(scenario):
    cfg = scenario.plant_config()
    _, params = parse_effect("load_transfer:bogie_height_m=2.6")
    plant = RealityPlant(cfg, {"load_transfer": params})
    states = trajectory(plant, plant.equilibrium_torque_nm, 300)
    mu, load = states[-1, 3], states[-1, 4]
    normal = load * 0.97 * 2.788 / (mu * 0.4375)
    # by hand, Table 1: a = z/(2 L_b) + Z/(4 L), b = mu_req N0 (z/(2 L_b) + 3 Z/(4 L))
    n0 = 13500 * 9.8
    a = 2.6 / 5.0 + 0.88 / 76.0
    b = 0.16 * n0 * (2.6 / 5.0 + 3 * 0.88 / 76.0)
    assert normal == pytest.approx((n0 - b) / (1 + a * mu), rel=1e-9)
    # the unloaded axle needs more mu for the same torque: it settles at a higher creep than nominal
    nom = trajectory(WheelsetPlant(cfg), plant.equilibrium_torque_nm, 300)
    assert states[-1, 2] > nom[-1, 2] + 0.01


def test_resistance_factor_slows_the_train_by_the_davis_force(scenario):
    cfg = scenario.plant_config()
    nom = WheelsetPlant(cfg)
    real = RealityPlant(cfg, {"resistance": {"factor": 2.0}})
    a = trajectory(nom, nom.equilibrium_torque_nm, 400)
    b = trajectory(real, real.equilibrium_torque_nm, 400)
    # an extra Davis force R(v) ~ R(10 m/s) = 2600 + 3500 + 7000 N over 0.4 s on 408 t
    expected = -(2600 + 350 * 10.2 + 70 * 10.2 ** 2) * 0.4 / 408000
    assert b[-1, 1] - a[-1, 1] == pytest.approx(expected, rel=0.03)


def test_torque_lag_delays_a_torque_step(scenario):
    cfg = scenario.plant_config()
    nom, lag = WheelsetPlant(cfg), RealityPlant(cfg, {"torque_lag": {"tau_s": 0.02}})
    t0 = nom.equilibrium_torque_nm
    step = t0 + 500.0
    d_nom = nom.step(step).motor_speed_rad_s - nom.x0[0]
    d_lag = lag.step(step).motor_speed_rad_s - lag.x0[0]
    # first period: nominal gains ~500/J_eq * 1 ms; with a 20 ms lag the extra torque has barely started
    base = WheelsetPlant(cfg)
    d_base = base.step(t0).motor_speed_rad_s - base.x0[0]
    assert (d_lag - d_base) < 0.1 * (d_nom - d_base)
    # and a constant command is not affected at all
    lag2 = RealityPlant(cfg, {"torque_lag": {"tau_s": 0.02}})
    assert np.allclose(trajectory(lag2, t0, 200), trajectory(WheelsetPlant(cfg), t0, 200), atol=1e-9)


def test_a_power_limit_caps_the_torque_at_power_over_speed(scenario):
    """The drive's constant-power region: T = min(T_cmd, P_max / omega_m).  Far above the equilibrium power
    it never binds (the nominal plant); at 0.98 of it, it binds from the start, and the motor then
    accelerates as under a torque of P_max / omega_m."""
    from plant.model import equilibrium
    cfg = scenario.plant_config()
    x0, t0 = equilibrium(cfg)
    far = RealityPlant(cfg, {"power_limit": {"power_kw": 10 * t0 * x0[0] * 1e-3, "power_ratio": 1.0}})
    assert np.allclose(trajectory(far, t0, 300), trajectory(WheelsetPlant(cfg), t0, 300), atol=1e-9)
    _, params = parse_effect("power_limit:power_ratio=0.98")
    capped = RealityPlant(cfg, {"power_limit": params})
    assert capped.effects["power_limit"]["power_kw"] == pytest.approx(0.98 * t0 * x0[0] * 1e-3, rel=1e-12)
    # the nominal plant commanded P_max / omega_m at each period's start (omega_m moves by < 1e-3 of
    # itself in a period, so the cap held per period is the cap to that order)
    nom = WheelsetPlant(cfg)
    p_w = params["power_ratio"] * t0 * x0[0]
    by_hand, w = [], x0[0]
    for _ in range(300):
        s = nom.step(min(t0, p_w / w))
        w = s.motor_speed_rad_s
        by_hand.append(w)
    got = trajectory(capped, t0, 300)[:, 0]
    assert np.max(np.abs(got - np.array(by_hand))) < 1e-4 * np.max(np.abs(np.array(by_hand) - x0[0]))
    assert got[-1] < trajectory(WheelsetPlant(cfg), t0, 300)[-1, 0] - 0.01   # and the cap slows the motor


def test_a_torque_map_takes_torque_off_in_proportion_to_the_speed_rise(scenario):
    """The drive's torque map: T = T_cmd max(1 - droop (omega_m / omega0 - 1), 0), omega0 the equilibrium
    speed by default.  The plant follows the nominal plant commanded that torque from each period's
    start (to the order a period moves omega_m), and a drooping map slows the motor."""
    from plant.model import equilibrium
    cfg = scenario.plant_config()
    x0, t0 = equilibrium(cfg)
    _, params = parse_effect("torque_map:droop=2.5")
    mapped = RealityPlant(cfg, {"torque_map": params})
    assert mapped.effects["torque_map"]["omega0_rad_s"] == pytest.approx(x0[0], rel=1e-12)
    nom = WheelsetPlant(cfg)
    by_hand, w = [], x0[0]
    for _ in range(700):                          # past the fault at 0.5 s, where the motor speeds up
        s = nom.step(t0 * max(1 - 2.5 * (w / x0[0] - 1), 0))
        w = s.motor_speed_rad_s
        by_hand.append(w)
    got = trajectory(mapped, t0, 700)[:, 0]
    assert np.max(np.abs(got - np.array(by_hand))) < 1e-3 * np.max(np.abs(np.array(by_hand) - x0[0]))
    assert got[-1] < trajectory(WheelsetPlant(cfg), t0, 700)[-1, 0] - 0.01


def test_compliance_rings_after_the_fault_only(scenario):
    cfg = scenario.plant_config()
    nom = WheelsetPlant(cfg)
    comp = RealityPlant(cfg, {"compliance": {"stiffness_nm_rad": 3e5, "damping_ratio": 0.03, "backlash_rad": 0.001}})
    a = trajectory(nom, nom.equilibrium_torque_nm, 650)
    b = trajectory(comp, comp.equilibrium_torque_nm, 650)
    pre = slice(0, 490)
    assert np.max(np.abs(a[pre, 0] - b[pre, 0])) < 1e-6     # initial twist consistent: no transient
    post = b[500:650, 0] - a[500:650, 0]
    assert np.max(np.abs(post)) > 0.02
    # the ring is at the two-inertia natural frequency sqrt(k (1/J_m + 1/J_w)) / (2 pi)
    j_w = 80 / (0.97 * 2.788 ** 2)
    f_n = math.sqrt(3e5 * (1 / 6 + 1 / j_w)) / (2 * math.pi)
    x = np.diff(b[500:650, 0])   # motor acceleration-like signal
    spec = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(x.size)))
    f = np.fft.rfftfreq(x.size, cfg.exchange_period_s)
    assert f[np.argmax(spec[1:]) + 1] == pytest.approx(f_n, rel=0.2)


def test_adhesion_lag_slows_the_fault_switch(scenario):
    cfg = scenario.plant_config()
    tau = 0.02
    nom, lag = WheelsetPlant(cfg), RealityPlant(cfg, {"adhesion_lag": {"tau_s": tau}})
    k_f = int(round(cfg.fault_time_s / cfg.exchange_period_s))
    a = trajectory(nom, nom.equilibrium_torque_nm, k_f + 1)
    b = trajectory(lag, lag.equilibrium_torque_nm, k_f + 1)
    mu_before, mu_nom_after, mu_lag_after = a[k_f - 2, 3], a[k_f, 3], b[k_f, 3]
    # nominal mu jumps to the fault curve; the lagged one has moved by about 1 - exp(-1 ms / tau)
    moved = (mu_before - mu_lag_after) / (mu_before - mu_nom_after)
    assert moved == pytest.approx(1 - math.exp(-cfg.exchange_period_s / tau), abs=0.02)


@pytest.mark.parametrize("creep_kmh", [0.5, 3.0, 5.0, 7.0])
def test_bristle_at_its_steady_deflection_is_on_the_curve_at_any_slip(scenario, creep_kmh):
    """LuGre: with the bristle at g = mu_curve / sigma0 and sliding forward, z' = 0 and mu = mu_curve,
    however fast it slides (the integration's cap on the relaxation rate must not move the steady state:
    it once turned the bristle into a viscous friction above a few km/h of slip)."""
    import casadi as ca
    from plant.params import KMH_PER_MS
    from plant.reality import RealityModel
    cfg = scenario.plant_config()
    p = cfg.params
    s0 = 60.0
    model = RealityModel(cfg, {"bristle": {"stiffness_per_m": s0, "damping_s_per_m": 0.01}})
    v_t = 20.0
    omega_m = (v_t + creep_kmh / KMH_PER_MS) / p.wheel_radius_m * p.gear_ratio
    t = cfg.fault_time_s + 0.1
    mu_curve = float(cfg.fault_curve.mu_at(creep_kmh, v_t))
    x = ca.DM([omega_m, v_t, mu_curve / s0])
    dx, mu, _, _ = model.rhs(x, 1000.0, t)
    assert float(dx[model.state_names.index("bristle_z")]) == pytest.approx(0.0, abs=1e-12)
    assert float(mu) == pytest.approx(mu_curve, rel=1e-9)


@pytest.mark.parametrize("low_creep_scale", [0.65, 1.35])
def test_a_rail_shape_changes_the_curve_at_low_creep_and_keeps_its_peak_and_tail(scenario, low_creep_scale):
    """Issue 51 item 4: ``rail_shape`` stretches (k > 1) or squeezes (k < 1) the fault curve near zero creep,
    mu = mu_fault(v_s / k(v_s)), k = 1 + (k0 - 1) exp(-|v_s| / knee).  Read off the plant's own dynamics
    (``RealityModel.rhs``, after the fault) against the fault curve and k by hand: at 0.05 km/h mu is the
    curve's at v_s / k and its slope the curve's over k (more than 20 % off); at 10 knees and more mu is
    the curve's within 1e-3; its peak is the curve's, and mu rises with creep up to it."""
    import casadi as ca
    from plant.params import KMH_PER_MS
    from plant.reality import RealityModel
    cfg = scenario.plant_config()
    p = cfg.params
    knee = 0.5
    model = RealityModel(cfg, {"rail_shape": {"low_creep_scale": low_creep_scale, "knee_kmh": knee}})
    v_t, t = 20.0, cfg.fault_time_s + 0.1

    def mu_at(creep_kmh):
        omega_m = (v_t + creep_kmh / KMH_PER_MS) / p.wheel_radius_m * p.gear_ratio
        return float(model.rhs(ca.DM([omega_m, v_t]), 1000.0, t)[1])

    curve = lambda c: float(cfg.fault_curve.mu_at(c, v_t))  # noqa: E731
    k = lambda c: 1 + (low_creep_scale - 1) * math.exp(-c / knee)  # noqa: E731   (by hand)
    for c in (0.05, 0.5, 2.0, 5.0):
        assert mu_at(c) == pytest.approx(curve(c / k(c)), rel=1e-9)
    low = 0.05
    slope_ratio = (mu_at(low) / low) / (curve(low) / low)      # the curve's slope near zero, over k
    assert slope_ratio == pytest.approx(1 / k(low), rel=0.03) and abs(slope_ratio - 1) > 0.2
    for c in (5.0, 7.0):                                        # 10 knees and more: the curve's tail
        assert mu_at(c) == pytest.approx(curve(c), rel=1e-3)
    grid = np.linspace(0.01, 3.0, 600)
    shaped = np.array([mu_at(c) for c in grid])
    assert shaped.max() == pytest.approx(max(curve(c) for c in grid), rel=1e-4)   # the same peak
    assert np.all(np.diff(shaped[grid <= 1.2]) > 0)             # ffcc_a's fault curve peaks at 1.27 km/h


def test_sensor_delay_and_quantisation():
    inner = SensorModel(SensorConfig(), seed=1)
    s = RealitySensors(inner, {"sensor_delay": {"delay_ms": 2.5}}, 1e-3)
    out = [s.measure(float(k), 10.0 + k)[0] for k in range(10)]
    assert out[5:] == pytest.approx([k - 2.5 for k in range(5, 10)])
    q = RealitySensors(SensorModel(SensorConfig(motor_speed_noise_rad_s=0.01), seed=2),
                       {"sensor_quantisation": {"motor_quantum_rad_s": 0.05, "train_quantum_ms": 0.0}}, 1e-3)
    vals = np.array([q.measure(64.0 + 0.003 * k, 10.0)[0] for k in range(200)])
    assert np.allclose(vals / 0.05, np.round(vals / 0.05), atol=1e-9)
    assert len(np.unique(vals)) > 5


def test_a_stuck_encoder_repeats_its_last_reading_for_its_hold_time():
    """``sensor_stick``: from reading start_s / period on, the motor encoder repeats the reading it made
    just before (noise included) for hold_ms; the train speed and every other reading are untouched."""
    period = 1e-3
    plain = SensorModel(SensorConfig(motor_speed_noise_rad_s=0.01), seed=3)
    stuck = RealitySensors(SensorModel(SensorConfig(motor_speed_noise_rad_s=0.01), seed=3),
                           {"sensor_stick": {"start_s": 0.02, "hold_ms": 7.0}}, period)
    a = np.array([plain.measure(60.0 + 0.1 * k, 10.0 + k) for k in range(40)])
    b = np.array([stuck.measure(60.0 + 0.1 * k, 10.0 + k) for k in range(40)])
    assert np.array_equal(b[:, 1], a[:, 1])
    assert np.array_equal(b[:20, 0], a[:20, 0]) and np.array_equal(b[27:, 0], a[27:, 0])
    assert np.all(b[20:27, 0] == a[19, 0])


def test_can_delay_jitter_loss():
    can = CanReality(delay_ms=3.0, jitter_ms=0.0, loss=0.0, period_s=1e-3, seed=1)
    got = [can.deliver(SensorReading(k, float(k), 0.0)) for k in range(20)]
    assert [g.step for g in got] == list(range(20))                 # re-stamped with the TCU's step
    assert [g.motor_speed_rad_s for g in got[3:]] == [float(k - 3) for k in range(3, 20)]
    # the first three periods reuse the initial frame (delays 0, 1, 2), then 3 periods each
    assert can.realised()["mean_delay_ms"] == pytest.approx((0 + 1 + 2 + 3 * 17) / 20)
    lossy = CanReality(delay_ms=1.0, jitter_ms=0.0, loss=0.3, period_s=1e-3, seed=5)
    vals = [lossy.deliver(SensorReading(k, float(k), 0.0)).motor_speed_rad_s for k in range(2000)]
    repeats = np.mean(np.diff(vals) == 0)
    assert repeats == pytest.approx(0.3, abs=0.04)
    assert lossy.realised()["lost_frames"] == pytest.approx(600, abs=80)
    assert np.all(np.diff(vals) >= 0)                               # never goes back to an older frame


def test_parse_effect_errors():
    assert parse_effect("can:delay_ms=4")[1] == {"delay_ms": 4.0, "jitter_ms": 0.0, "loss": 0.0}
    for bad, word in (("bogus", "unknown effect"), ("can:nope=1", "unknown parameter"),
                      ("can:delay_ms=x", "expected a number"), ("can:delay_ms", "PARAM=VALUE"),
                      ("adhesion_lag:tau_s=0", "must be > 0"), ("can:loss=1", "must be < 1")):
        with pytest.raises(ValueError, match=word):
            parse_effect(bad)


def test_run_records_truth_under_one_key(scenario, tmp_path):
    real = with_reality(scenario, {"resistance": {"factor": 1.7}, "can": {"delay_ms": 2.0}})
    summary = run(real, "nlls", 3, bus="inprocess", out_dir=tmp_path, progress=False, log=print)
    log = read_log(summary["mcap"])
    truth = log.metadata[TRUTH_KEY]
    assert json.loads(truth["effects"]) == {"resistance": {"factor": 1.7},
                                            "can": {"delay_ms": 2.0, "jitter_ms": 0.0, "loss": 0.0}}
    others = json.dumps({k: v for k, v in log.metadata.items() if k != TRUTH_KEY})
    assert "resistance" not in others and "factor" not in others and "delay_ms" not in others
    nominal = run(scenario, "nlls", 3, bus="inprocess", out_dir=tmp_path / "nom", progress=False, log=print)
    assert TRUTH_KEY not in read_log(nominal["mcap"]).metadata


def test_cli_reality_flag(tmp_path, ffcc_a_path):
    r = subprocess.run(hil_command() + ["run", str(ffcc_a_path), "--reality", "bogus:x=1", "--out", str(tmp_path)],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "unknown effect 'bogus'" in r.stderr
    r = subprocess.run(hil_command() + ["run", str(ffcc_a_path), "--reality", "adhesion_lag:tau_s=0.01",
                                        "--out", str(tmp_path), "--json"],
                       capture_output=True, text=True, env=subprocess_env(), timeout=120)
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    truth = read_log(s["mcap"]).metadata[TRUTH_KEY]
    assert json.loads(truth["effects"]) == {"adhesion_lag": {"tau_s": 0.01}}


def test_the_effect_registry_and_the_physics_name_the_same_effects():
    """hil/effects.py says which effects exist and at which level; plant/reality.py integrates the plant
    and sensor ones: the two lists must agree."""
    from hil.effects import EFFECTS
    from plant.reality import SENSOR_EFFECTS, plant_order

    assert {n for n, s in EFFECTS.items() if s.level == "plant"} == set(plant_order())
    assert {n for n, s in EFFECTS.items() if s.level == "sensor"} == set(SENSOR_EFFECTS)
    assert {n for n, s in EFFECTS.items() if s.level == "bus"} == {"can"}
