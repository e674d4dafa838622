"""The CasADi plant against independent physics: hand-computed equilibria, an independent
scipy integration of the same ODE, the fault stages."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from hil.config import load_scenario
from plant import FrictionCurve, SensorConfig, SensorModel, StageTracker, WheelsetPlant


def test_paper_curves_peak_where_the_paper_says(ffcc_a_path, ffcc_b_path):
    a = load_scenario(ffcc_a_path).fault_curve
    b = load_scenario(ffcc_b_path).fault_curve
    # method.md: FFCC-a peaks at mu 0.152 near 1.27 km/h, FFCC-b at 0.143 near 1.25 km/h,
    # and FFCC-b gives mu ~ 0.04 at 4.8 km/h
    assert a.peak() == pytest.approx((1.27, 0.152), abs=0.01)
    assert b.peak() == pytest.approx((1.25, 0.143), abs=0.01)
    assert float(b.mu(4.8)) == pytest.approx(0.04, abs=0.002)


def test_curve_with_three_terms_evaluates_each_term():
    c = FrictionCurve(0.01, (0.5, -0.3, -0.2), (-0.4, -1.0, -2.0))
    v = np.array([0.0, 1.0, 3.0])
    expected = 0.01 + 0.5 * np.exp(-0.4 * v) - 0.3 * np.exp(-1.0 * v) - 0.2 * np.exp(-2.0 * v)
    np.testing.assert_allclose(c.mu(v), expected, rtol=1e-14)


def test_equilibrium_holds_creep_before_the_fault(ffcc_a_path):
    sc = load_scenario(ffcc_a_path)
    plant = WheelsetPlant(sc.plant_config())
    v0 = plant.state.creep_speed_kmh
    assert float(sc.normal_curve.mu(v0)) == pytest.approx(0.16, abs=1e-9)
    for _ in range(400):            # 0.4 s, all before t_f = 0.5 s
        s = plant.step(plant.equilibrium_torque_nm)
    assert s.creep_speed_kmh == pytest.approx(v0, abs=2e-3)
    assert s.mu == pytest.approx(0.16, abs=1e-3)
    assert s.train_speed_ms > sc.run.initial_train_speed_ms   # the train accelerates


def test_plant_matches_independent_integration(ffcc_b_path):
    """Same ODE written again from method.md §1 with numpy, integrated by scipy's RK45 at tight tolerance."""
    sc = load_scenario(ffcc_b_path)
    p, run = sc.vehicle, sc.run
    plant = WheelsetPlant(sc.plant_config())
    torque = plant.equilibrium_torque_nm
    j_eq = p.motor_inertia_kgm2 + p.wheelset_inertia_kgm2 / (p.efficiency * p.gear_ratio ** 2)
    n_force = p.axle_load_kg * p.gravity_ms2

    def rhs(t, x, curve):
        v_s = 3.6 * (x[0] / p.gear_ratio * p.wheel_radius_m - x[1])
        mu = float(curve.mu(v_s))
        t_l = mu * n_force * p.wheel_radius_m / (p.efficiency * p.gear_ratio)
        resist = p.davis_a_n + p.davis_b_n_per_ms * x[1] + p.davis_c_n_per_ms2 * x[1] ** 2
        f_train = mu * n_force + (p.driven_axles - 1) * run.mu_required * n_force - resist
        return [(torque - t_l) / j_eq, f_train / p.train_mass_kg]

    x0 = plant.x0
    pre = solve_ivp(rhs, (0, run.fault_time_s), x0, args=(sc.normal_curve,), rtol=1e-11, atol=1e-11)
    post = solve_ivp(rhs, (run.fault_time_s, 0.6), pre.y[:, -1], args=(sc.fault_curve,), rtol=1e-11, atol=1e-11,
                     dense_output=True)
    for _ in range(600):
        s = plant.step(torque)
    ref = post.sol(0.6)
    assert s.motor_speed_rad_s == pytest.approx(ref[0], rel=1e-6)
    assert s.train_speed_ms == pytest.approx(ref[1], rel=1e-7)


def test_stage_tracking_finds_serious_stage_tens_of_ms_after_fault(ffcc_a_path, ffcc_b_path):
    for path, lo, hi in ((ffcc_a_path, 0.05, 0.10), (ffcc_b_path, 0.025, 0.07)):
        sc = load_scenario(path)
        plant = WheelsetPlant(sc.plant_config())
        tracker = StageTracker(sc.run.fault_time_s, sc.fault_curve.peak()[0])
        stages = []
        for _ in range(700):
            s = plant.step(plant.equilibrium_torque_nm)
            stages.append(tracker.update(s.t_s, s.creep_speed_kmh))
        assert stages[0] == "normal" and stages[-1] == "serious" and "early" in stages
        assert lo < tracker.deterioration_time_s < hi
        # the serious stage starts exactly where the creep first passes the peak creep
        k = stages.index("serious")
        assert stages[k - 1] == "early"


def test_sensor_noise_is_seeded_and_quantised():
    cfg = SensorConfig(motor_speed_noise_rad_s=0.1, train_speed_noise_ms=0.0, motor_speed_quantum_rad_s=0.05)
    a = [SensorModel(cfg, 7).measure(50.0, 10.0) for _ in range(3)]
    m1, m2 = SensorModel(cfg, 7), SensorModel(cfg, 7)
    seq1 = [m1.measure(50.0, 10.0)[0] for _ in range(50)]
    seq2 = [m2.measure(50.0, 10.0)[0] for _ in range(50)]
    assert seq1 == seq2
    assert len(set(seq1)) > 3                                # noise present
    assert all(abs(x / 0.05 - round(x / 0.05)) < 1e-9 for x in seq1)   # on the quantisation grid
    assert SensorModel(cfg, 8).measure(50.0, 10.0) != a[0]


def test_a_rail_stepped_by_windows_of_segments_is_the_whole_rail_to_the_bit():
    """The wet patch with a recovering segment, its torque swept across the patch: every period's state, mu
    and creep from the plant (a function of only the segments that weigh in each period) equal the whole
    rail's function to the bit, and stepping through every change of rail builds no function (a build in the
    loop made a real-time run miss deadlines at each change)."""
    from pathlib import Path

    from plant.model import build_period_step

    sc = load_scenario(Path(__file__).parents[1] / "scenarios" / "wet_patch.toml",
                       {"rail.1.recovers_to": 0, "rail.1.energy_clean_j": 2e5})
    cfg = sc.plant_config()
    plant = WheelsetPlant(cfg)
    built = dict(plant._steps)
    whole = build_period_step(cfg)
    torque0 = plant.equilibrium_torque_nm
    for k in range(sc.steps):
        torque = torque0 * (1.3 + 0.3 * np.sin(k / 300))
        x, t0, rho = plant._x_out.copy(), plant.t_s, plant._cleaned.copy()
        plant.step(torque)
        x_ref, mu_ref, creep_ref = whole(x, torque, t0, rho)
        assert np.array_equal(np.r_[plant._x_out, plant._mu_out, plant._creep_out],
                              np.r_[np.array(x_ref).ravel(), float(mu_ref), float(creep_ref)]), f"step {k}"
    assert len(built) == 5 and plant._steps.keys() == built.keys()
    assert plant.cleaned[0] > 0.5      # the recovery did act: rho entered the windows' functions


def test_a_curves_peak_and_stable_inverse_agree_with_scipy_on_drawn_curves():
    """``peak`` (golden-section search) and ``creep_for_mu`` (bisection) are plain Python so that the plant
    does not import scipy.optimize at start-up; scipy's bounded Brent and brentq are the reference here, on
    curves drawn from the default family (exponential and Polach), the seed printed."""
    from scipy.optimize import brentq, minimize_scalar

    from plant.families import sample_curves
    from plant.friction import PEAK_SEARCH_KMH

    from .conftest import case_seed

    seed = case_seed("peak-vs-scipy")
    batch = sample_curves("default", 40, np.random.default_rng(seed), 20.0)
    print(f"seed {seed}")
    grid = np.linspace(*PEAK_SEARCH_KMH, 3001)
    for i in range(len(batch)):
        c = batch.curve(i)
        v, mu = c.peak()
        k = int(np.argmax(c.mu(grid)))
        ref = minimize_scalar(lambda x: -float(c.mu(x)), bounds=(grid[k - 1], grid[k + 1]), method="bounded",
                              options={"xatol": 1e-10})
        assert v == pytest.approx(ref.x, abs=2e-6) and mu == pytest.approx(-ref.fun, rel=1e-12), (seed, i)
        target = 0.8 * mu + 0.2 * float(c.mu(0.0))
        root = brentq(lambda x: float(c.mu(x)) - target, 0.0, v, xtol=1e-13)
        assert c.creep_for_mu(target) == pytest.approx(root, abs=1e-11), (seed, i)


def test_the_truths_peak_over_a_transition_and_a_recovery_is_the_uncached_search_to_the_bit():
    """The rail's true peak (``RailSchedule.peak``, asked every period) keeps each curve's values on its search
    grid across a transition and a recovery; every period's (peak creep, peak mu) equals the same search made
    afresh by a schedule with nothing kept, while the train speed moves a Polach curve's peak."""
    import copy

    from plant.friction import PolachCurve
    from plant.rail import RailSchedule, RailSegment, Recovery

    dry = PolachCurve(0.3, 0.3, 0.8, 0.7, 0.5, 60.0, 10.0)
    wet = PolachCurve(0.12, 0.5, 0.6, 0.6, 0.4, 25.0, 10.0)
    rail = RailSchedule((RailSegment(0.0, dry), RailSegment(1.0, wet, 0.4, "wet")), {1: Recovery(2e5, dry)})
    peaks = set()
    for k, t_s in enumerate(np.arange(0.95, 1.6, 0.007)):
        v_t = 10.0 + 0.13 * k                      # a train speed that moves the peak: new grid rows are made too
        cleaned = (min(0.9, 0.011 * k),)           # a patch being cleaned
        fresh = copy.deepcopy(rail)
        fresh._cache.clear()
        fresh._grid_cache.clear()
        peak = rail.peak(t_s, v_t, cleaned)
        assert peak == fresh.peak(t_s, v_t, cleaned), (k, t_s)
        peaks.add(peak)
    assert len(peaks) > 50                          # the peak did move with the speed, the blend and the cleaning
    assert rail._grid_cache and all(not a.flags.writeable for a in rail._grid_cache.values())
