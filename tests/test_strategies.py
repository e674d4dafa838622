"""Identification strategies on synthetic samples: recovery, projection, evaluation, robustness, seeding."""
import math

import numpy as np
import pytest

from identifier import STRATEGIES, IdentifierSettings, VehicleModel, make_strategy
from identifier import pf
from identifier.curve import mu_model
from identifier.metrics import peak_errors
from identifier.strategies import Sample, Strategy
from identifier.strategies.mdipf import MdipfStrategy

FFCC_A = np.array([-0.005, 0.585, -0.580, -0.525, -1.100])
NFCC_0 = (0.0, 1.0, -1.0, -0.54, -1.2)
# the MDIPF family (prelim + filter over error vectors); bayes has tests of its own (tests/test_bayes.py)
PF_STRATEGIES = [s for s in STRATEGIES if issubclass(STRATEGIES[s], MdipfStrategy)]
# observer-aware strategies model the observer's transient: fed with static (v, mu) pairs in random order
# they are fitting the wrong model; tests/test_observer_aware.py feeds them a simulated plant + observer
STATIC_STRATEGIES = [s for s in STRATEGIES if not STRATEGIES[s].observer_aware]


def settings(**kw) -> IdentifierSettings:
    vehicle = VehicleModel(equivalent_inertia_kgm2=16.6, torque_per_mu_nm=21373.0, gear_ratio=2.788,
                           wheel_radius_m=0.4375)
    return IdentifierSettings(period_s=1e-3, vehicle=vehicle, torque_demand_nm=3400.0, initial_guess=NFCC_0, **kw)


def samples_spanning_peak(n=240, noise=3e-4, seed=7, theta=FFCC_A):
    """Creep speeds over 0.2..2.6 km/h (the peak is at 1.27) in random order, mu on the curve + noise."""
    rng = np.random.default_rng(seed)
    v = rng.permutation(np.linspace(0.2, 2.6, n))
    mu = mu_model(v, theta) + rng.normal(0.0, noise, n)
    return [Sample(k, k * 1e-3, float(a), float(b)) for k, (a, b) in enumerate(zip(v, mu))]


def feed(strategy: Strategy, samples):
    events = []
    for s in samples:
        events.extend(strategy.add_sample(s))
    return events


def assert_confirmed_near_the_peak(strat: Strategy, events, theta=FFCC_A):
    """Confirmed, with the peak within 3 % in mu and 10 % in creep speed of the curve ``theta``."""
    assert strat.confirmed, f"{strat.name} did not confirm after {strat.corrections} corrections"
    assert events[-1].kind == "confirmed"
    err = peak_errors(strat.theta, theta)
    assert err["peak_mu_err_percent"] < 3.0 and err["peak_creep_err_percent"] < 10.0, err


@pytest.mark.parametrize("name", sorted(STATIC_STRATEGIES))
def test_each_strategy_recovers_a_known_curve(name):
    strat = make_strategy(name, settings(), seed=3)
    assert_confirmed_near_the_peak(strat, feed(strat, samples_spanning_peak(600)))
    grid = np.linspace(0.2, 2.6, 50)
    assert np.max(np.abs(mu_model(grid, strat.theta) - mu_model(grid, FFCC_A))) < 0.005
    if name == "proposed_mu0":
        assert abs(strat.theta[0] + strat.theta[1] + strat.theta[2]) < 1e-9     # mu(0) = 0 kept exactly


def test_projection_puts_every_particle_inside_the_box():
    rng = np.random.default_rng(0)
    lo, hi = np.array([-0.01, -0.05, -0.05, -0.1, -0.1]), np.array([0.01, 0.05, 0.05, 0.1, 0.1])
    particles = rng.normal(0.0, 0.3, (500, 5))
    particles[0, 2] = np.nan
    particles[1, 4] = np.inf
    particles[2, :] = -np.inf
    inside_before = np.all((particles >= lo) & (particles <= hi), axis=1)
    for method in pf.PROJECTORS:
        out = pf.project_to_box(particles, lo, hi, FFCC_A, 0.8, 0.14, np.full(5, 0.02), 0.002, method)
        assert np.all(np.isfinite(out))
        assert np.all((out >= lo) & (out <= hi)), method
        # particles already inside are left where they were
        np.testing.assert_array_equal(out[inside_before], particles[inside_before])


def test_map_projection_moves_edge_particles_towards_the_measurement():
    lo, hi = -np.full(5, 0.05), np.full(5, 0.05)
    particles = np.tile([0.0, 0.3, 0.0, 0.0, 0.0], (4, 1))      # lambda1 far outside: curve much too high
    z = float(mu_model(np.array([0.8]), FFCC_A)[0])
    clip = pf.project_to_box(particles, lo, hi, FFCC_A, 0.8, z, np.full(5, 0.05), 0.001, "clip")
    mapped = pf.project_to_box(particles, lo, hi, FFCC_A, 0.8, z, np.full(5, 0.05), 0.001, "map")
    err = lambda x: np.abs(pf.curve_at(x, FFCC_A, 0.8) - z)       # noqa: E731
    assert np.all(err(mapped) < err(clip))


def test_proposed_cloud_stays_in_its_box_while_filtering():
    strat = make_strategy("proposed", settings(), seed=1)
    for s in samples_spanning_peak(60):
        strat.add_sample(s)
        if strat.prelim_done:
            assert np.all((strat.particles >= strat.lo - 1e-12) & (strat.particles <= strat.hi + 1e-12))
    assert strat.prelim_done and strat.boxes, "the box never contracted"
    first, last = strat.boxes[0], strat.boxes[-1]
    assert np.all(last[1] - last[0] <= first[1] - first[0] + 1e-12)


class FixedCurve(Strategy):
    """Always proposes the same curve: J_EF is 0 from the second correction on."""

    name = "fixed"

    def correct(self, window_v, window_mu):
        return FFCC_A.copy()


def window(v_values, offset=0.0, start=0):
    v = np.asarray(v_values, float)
    mu = mu_model(v, FFCC_A) + offset + 1e-4 * np.sin(np.arange(v.size))   # SE > 0
    return [Sample(start + k, (start + k) * 1e-3, float(a), float(b)) for k, (a, b) in enumerate(zip(v, mu))]


def test_multilevel_evaluation_confirms_only_when_the_next_window_fits():
    s = settings(window_samples=8)
    strat = FixedCurve(s)
    v = np.linspace(0.4, 1.0, 8)
    assert [e.kind for e in feed(strat, window(v))] == ["correction"]          # J_EF = inf
    assert [e.kind for e in feed(strat, window(v + 0.1, start=8))] == ["correction"]   # J_EF = 0: candidate
    # the next window lies 0.01 above the curve (>> 3 SE): no confirmation, it feeds a correction
    kinds = [e.kind for e in feed(strat, window(v + 0.2, offset=0.01, start=16))]
    assert kinds == ["correction"] and not strat.confirmed
    # the window after that fits the candidate: confirmed at its end, not before
    w = window(v + 0.3, start=24)
    assert feed(strat, w[:-1]) == [] and not strat.confirmed
    assert [e.kind for e in feed(strat, w[-1:])] == ["confirmed"] and strat.confirmed


def test_k_pe_gates_the_confidence_check():
    strat = FixedCurve(settings(window_samples=8, k_pe=-1.0))      # no J_EF can pass
    for k in range(6):
        feed(strat, window(np.linspace(0.4, 1.0, 8) + 0.05 * k, start=8 * k))
    assert not strat.confirmed and strat.corrections == 6


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("name", PF_STRATEGIES)
def test_bad_samples_and_degenerate_weights_never_give_nan_parameters(name, compiled):
    # tiny G makes every likelihood underflow; huge and non-finite samples in between
    s = settings(options={name: {"noise_std": 1e-9, "particles": 200, "compiled": compiled}})
    strat = make_strategy(name, s, seed=0)
    good = samples_spanning_peak(40)
    bad = [Sample(1000 + k, 1.0, v, m) for k, (v, m) in
           enumerate([(math.nan, 0.1), (0.5, math.inf), (-math.inf, 0.1), (0.8, 1e6), (1e6, 0.1), (0.7, -1e6)])]
    for k, smp in enumerate(good):
        strat.add_sample(smp)
        if k % 5 == 0:
            for b in bad:
                strat.add_sample(b)
        assert np.all(np.isfinite(strat.theta)), f"NaN parameters after sample {k}"
        if strat.prelim_done:
            assert np.all(np.isfinite(strat.particles)) and np.all(np.isfinite(strat.weights))
            assert abs(strat.weights.sum() - 1.0) < 1e-9


def test_normalise_handles_all_degenerate_log_weights():
    for lw in (np.full(10, -np.inf), np.full(10, np.nan), np.r_[np.nan, np.full(9, -np.inf)]):
        w = pf.normalise(lw)
        np.testing.assert_allclose(w, np.full(10, 0.1))
    w = pf.normalise(np.r_[0.0, -np.inf, np.nan, -1000.0])
    assert w[0] == pytest.approx(1.0) and np.all(np.isfinite(w))


@pytest.mark.parametrize("name", PF_STRATEGIES)
def test_same_seed_same_result(name):
    data = samples_spanning_peak(40)
    runs = []
    for seed in (5, 5, 6):
        strat = make_strategy(name, settings(), seed=seed)
        feed(strat, data)
        runs.append(strat.theta.copy())
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])


def test_resampling_schemes_follow_the_weights():
    rng = np.random.default_rng(0)
    w = np.array([0.7, 0.0, 0.3, 0.0])
    for scheme in pf.RESAMPLERS:
        idx = np.concatenate([pf.resample(w, rng, scheme) for _ in range(500)])
        assert set(np.unique(idx)) <= {0, 2}
        assert abs(np.mean(idx == 0) - 0.7) < 0.03, scheme


@pytest.mark.parametrize("stabiliser", ["rownorm", "spectral"])
def test_correlation_transition_does_not_amplify(stabiliser):
    rng = np.random.default_rng(1)
    base = rng.normal(size=(1000, 1))
    cloud = np.hstack([base + 0.01 * rng.normal(size=(1000, 1)) for _ in range(5)])   # all strongly correlated
    w = np.full(1000, 1e-3)
    raw = pf.correlation_transition(cloud, w, "raw")
    assert np.max(np.abs(np.linalg.eigvals(raw))) > 4.0          # the literal matrix would amplify ~5x
    theta = pf.correlation_transition(cloud, w, stabiliser)
    assert np.max(np.abs(np.linalg.eigvals(theta))) <= 1.0 + 1e-9


@pytest.mark.parametrize("table, word", [("[identifier.options.proposed]\nbogus = 1\n", "bogus"),
                                         ("[identifier.options.proposed]\nparticles = \"many\"\n", "many"),
                                         ("[identifier.options.magic]\nparticles = 10\n", "magic")])
def test_bad_strategy_options_fail_at_scenario_load(ffcc_a_path, table, word):
    from hil.config import ScenarioError, parse_scenario

    text = ffcc_a_path.read_text() + "\n" + table
    with pytest.raises(ScenarioError) as e:
        parse_scenario(text, "x.toml")
    msg = str(e.value)
    assert "\n" not in msg and "x.toml" in msg and "[identifier.options." in msg and word in msg


def test_strategy_options_from_a_scenario_reach_the_strategy(ffcc_a_path):
    from hil.config import parse_scenario

    text = ffcc_a_path.read_text() + "\n[identifier.options.proposed]\nparticles = 123\nwindow_samples = 7\n"
    s = parse_scenario(text, "x.toml").identifier_settings()
    strat = make_strategy("proposed", s)
    assert strat.n_particles == 123 and strat.particles.shape == (123, 5) and strat.window_samples == 7
    assert make_strategy("mdipf", s).n_particles == 1000          # other strategies keep their defaults


@pytest.mark.parametrize("name", ["mdipf", "proposed"])
def test_spread_prelim_makes_the_same_filter_steps_only_later(name):
    """prelim_polish_per_sample > 0 spreads the prelim's lattice and LM polish over samples and has the
    filter catch up on the samples fed meanwhile: the same corrections and curve as the prelim done at
    once on window 1's last sample (up to rounding), only the prelim's own correction event comes later.
    (The numpy path: the compiled one solves the whole prelim on window 1's last sample.)"""
    samples = samples_spanning_peak(600)
    runs = {}
    for per_sample in (0, 3):
        opts = {"prelim_polish_per_sample": per_sample, "compiled": False}
        strat = make_strategy(name, settings(options={name: opts}), seed=5)
        runs[per_sample] = (strat, feed(strat, samples))
    (at_once, ev0), (spread, ev3) = runs[0], runs[3]
    assert spread.confirmed == at_once.confirmed and spread.corrections == at_once.corrections >= 2
    np.testing.assert_allclose(spread.theta, at_once.theta, rtol=0, atol=1e-9)
    assert [e.kind for e in ev3] == [e.kind for e in ev0]
    # the first correction (the prelim) is reported later; every later event on the same sample
    assert ev3[0].samples > ev0[0].samples == spread.window_samples
    assert [e.samples for e in ev3[1:]] == [e.samples for e in ev0[1:]]


def test_spread_prelim_keeps_window_end_work_off_single_samples():
    """Per sample while the prelim is spread: at most prelim_polish_per_sample LM iterations, and after it
    at most catch_up_per_sample filter steps (counted, not timed).  The numpy path (the compiled one
    needs no spreading: tests/test_kernels.py)."""
    strat = make_strategy("mdipf", settings(options={"mdipf": {"compiled": False}}), seed=5)
    steps, iters = [], []
    orig_step = strat._step
    counter = {"steps": 0}

    def counting_step(v, mu):
        counter["steps"] += 1
        orig_step(v, mu)

    strat._step = counting_step
    for s in samples_spanning_peak(60):
        job = strat._job
        before_left = job.left if job is not None else None
        counter["steps"] = 0
        strat.add_sample(s)
        steps.append(counter["steps"])
        if before_left is not None:
            iters.append(before_left - (job.left if job is not None else 0))
    assert max(iters) <= strat.opts["prelim_polish_per_sample"] and sum(iters) > 0
    assert max(steps) <= strat.opts["catch_up_per_sample"]
    assert strat.prelim_done and not strat._queue


def test_proposed_latest_confirms_when_proposed_does_and_reports_one_more_correction():
    """Same seed, same samples: the same corrections and confirmation sample as ``proposed``; the
    confirmed curve is the checked candidate moved by the filter's estimate over the confirmation
    window (so it differs from the last correction's curve), where ``proposed`` reports the candidate."""
    samples = samples_spanning_peak(300)
    paper, latest = make_strategy("proposed", settings(), seed=4), make_strategy("proposed_latest", settings(), seed=4)
    ev_p, ev_l = feed(paper, samples), feed(latest, samples)
    assert [(e.kind, e.samples) for e in ev_p] == [(e.kind, e.samples) for e in ev_l]
    assert ev_p[-1].kind == "confirmed"
    assert ev_p[-1].params == ev_p[-2].params                   # the paper: the candidate itself
    assert ev_l[-1].params != ev_l[-2].params                   # one more correction
    np.testing.assert_allclose(ev_l[-2].params, ev_p[-2].params, rtol=0, atol=1e-12)
    step = np.asarray(ev_l[-1].params) - np.asarray(ev_l[-2].params)
    assert np.all(np.abs(step) <= np.array([0.01, 0.06, 0.06, 0.09, 0.09]) + 1e-12)   # within the box


@pytest.mark.parametrize("key, value", [("particles", 1), ("init_std", [0.003, math.nan, 0.03]),
                                        ("transition_std", -0.001), ("noise_std", 0.0), ("noise_std", math.inf)])
def test_bad_filter_tuning_is_refused_by_name(key, value):
    with pytest.raises(ValueError, match=key):
        make_strategy("proposed", settings(options={"proposed": {key: value}}), 0)


def test_every_particle_strategy_declares_what_it_replaces():
    """The compiled fast paths of the MDIPF family run only where a class keeps the plain pieces;
    each class declares that in its ``plain_*`` flags (no identity checks at run time).  Here every
    class's flags are checked against what it really overrides, so a new variant cannot silently
    take a fast path that skips its own code."""
    from identifier.strategies import STRATEGIES, MdipfStrategy, ProposedStrategy

    groups = {"plain_step": ("_step", "_constrain", "_move", "_log_likelihood", "_weigh"),
              "plain_constrain": ("_constrain", "_constrain_in_box"),
              "plain_projection": ("_project",),
              "plain_prelim": ("preliminary_fit",),
              "plain_recentre": ("_after_recentre",)}
    checked = 0
    for name, cls in STRATEGIES.items():
        if not issubclass(cls, MdipfStrategy):
            continue
        base = ProposedStrategy if issubclass(cls, ProposedStrategy) else MdipfStrategy
        for flag, methods in groups.items():
            # the methods a base of the family defines itself count as plain for that base
            overridden = [m for m in methods if hasattr(base, m) and getattr(cls, m) is not getattr(base, m)
                          and not (m in ("_constrain",) and getattr(cls, m) is getattr(MdipfStrategy, m))]
            if overridden:
                assert getattr(cls, flag) is False, (name, flag, overridden)
            checked += 1
    assert checked >= 5 * 6


def test_strategies_are_imported_when_first_asked_for_and_the_plant_side_never_imports_them():
    """``identifier.strategies`` is a table (name -> module, class): a process that only needs the names (the
    plant, ``hil check``, the CLI's help) does not import scipy.optimize (about 0.4 s a process); asking for a
    class imports its module once, and every name of the package still resolves."""
    import subprocess
    import sys

    code = ("import sys, hil.exchange, hil.session, hil.cli\n"
            "from identifier import STRATEGIES, DEFAULT_STRATEGY\n"
            "names = sorted(STRATEGIES); assert DEFAULT_STRATEGY in STRATEGIES and len(names) == len(STRATEGIES)\n"
            "print('scipy.optimize' in sys.modules, ','.join(names))\n"
            "from identifier.strategies import GpStrategy, fit_curve\n"
            "print('scipy.optimize' in sys.modules, STRATEGIES['gp'] is GpStrategy is STRATEGIES['gp'])\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    before, after = r.stdout.splitlines()
    assert before.split() == ["False", ",".join(sorted(STRATEGIES))]
    assert after == "True True"
    from identifier.strategies import PRESETS
    for name, (base, changes, _) in PRESETS.items():
        assert issubclass(STRATEGIES[name], STRATEGIES[base]) and STRATEGIES[name].name == name
        assert STRATEGIES[name].defaults == {**STRATEGIES[base].defaults, **changes}
