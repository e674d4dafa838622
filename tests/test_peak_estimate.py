"""The predictive peak estimate (identifier/peak_estimate.py) on rails that change: its 90 % peak-creep intervals
on a drawn batch of dry -> patch -> dry sequences, the creep as a closed loop or the driver's demand leaves it."""
from __future__ import annotations

import math

import numpy as np

from identifier.peak_estimate import PeakEstimator
from plant.families import exp_coefficients, sample_curves

from .conftest import case_seed


def _exp_curve(rng, peak_mu, peak_creep_kmh, asymptote_ratio, term_ratio):
    l0, l1, l2, t1, t2 = (float(x) for x in exp_coefficients(peak_mu, peak_creep_kmh, 0.0, rng.uniform(*asymptote_ratio),
                                                            math.exp(rng.uniform(*np.log(term_ratio)))))
    return lambda v: l0 + l1 * np.exp(t1 * v) + l2 * np.exp(t2 * v)


def _rising_creep_kmh(mu, peak_creep_kmh, level):
    """The creep on mu's rising branch where mu reaches ``level`` (the peak creep if it never does)."""
    grid = np.linspace(1e-3, peak_creep_kmh, 2000)
    return float(grid[min(int(np.searchsorted(mu(grid), level)), grid.size - 1)])


def _sequence(rng):
    """One drawn case, as the bench's default family draws its rails (hil/benchmarks/control.py): a dry exp rail
    (peak mu 0.25-0.35 at 0.8-4 km/h), a leaf/oil patch (0.03-0.08 at 0.2-0.6 km/h) or a wet one (the ``default``
    fault family) with probability 1/2 each, the dry rail again; the demand at 50-95 % of the dry peak mu."""
    mp, vp = rng.uniform(0.25, 0.35), math.exp(rng.uniform(math.log(0.8), math.log(4.0)))
    dry = _exp_curve(rng, mp, vp, (0.25, 0.5), (1.8, 3.0))
    if rng.uniform() < 0.5:
        pm, pv = rng.uniform(0.03, 0.08), math.exp(rng.uniform(math.log(0.2), math.log(0.6)))
        patch = _exp_curve(rng, pm, pv, (0.3, 0.7), (1.5, 4.0))
    else:
        batch = sample_curves("default", 1, rng, 10.0)
        pm, pv = float(batch.peak_mu[0]), float(batch.peak_creep_kmh[0])
        patch = lambda v: batch.mu(np.atleast_1d(np.asarray(v, float)))[0]      # noqa: E731
    return dry, vp, patch, pm, pv, rng.uniform(0.5, 0.95) * mp


def _covered(rng, case) -> tuple[bool, bool]:
    """Whether the final estimate's 90 % peak-creep interval holds the true peak creep at the end of the patch
    (1.5 s) and of the dry rail after it (1.5 s).  The demand carries the dry rail (2 s at one creep: mu^ is the
    demand); on a patch that carries it too, the creep moves to where the patch gives the demand (mu^ unchanged);
    on one that does not, the creep drops to half and climbs at 4 km/h/s to 0.95 x its peak creep with a 0.05 km/h
    dither (a closed loop's scan); back on the dry rail, the creep returns to where the demand held it.  The
    sensors' noise on every sample (1 kHz)."""
    dry, vp, patch, pm, pv, demand_mu = case
    v1 = _rising_creep_kmh(dry, vp, demand_mu)
    carried = pm > 1.02 * demand_mu
    v2 = _rising_creep_kmh(patch, pv, demand_mu) if carried else 0.0
    est, step = PeakEstimator(1e-3), 0

    def feed(v, m):
        nonlocal step
        step += 1
        return est.add(step, step * 1e-3, v + 0.0075 * rng.standard_normal(), m + 0.001 * rng.standard_normal())

    for _ in range(2000):
        feed(v1, demand_mu)
    v = v1
    for j in range(1500):
        if carried:
            v += 0.02 * (v2 - v)
            e = feed(v, demand_mu)
        else:
            v = v + 0.1 * (0.5 * v1 - v) if j < 100 else min(v + 0.004, max(v, 0.95 * pv))
            x = v + 0.05 * math.sin(2.0 * math.pi * 10.0 * j * 1e-3)
            e = feed(x, float(np.asarray(patch(x)).ravel()[0]))
    on_patch = e.peak_creep_ci[0] <= pv <= e.peak_creep_ci[1]
    for _ in range(1500):
        v += 0.02 * (v1 - v)
        e = feed(v, demand_mu)
    return on_patch, e.peak_creep_ci[0] <= vp <= e.peak_creep_ci[1]


def test_the_estimates_90_percent_intervals_cover_rails_that_change():
    """150 drawn dry -> patch -> dry sequences (seed printed; ``_covered``): the 90 % peak-creep interval holds the
    true peak creep at the patch's end in at least 85 % of them and back on the dry rail in at least 62 %.
    Measured (2026-11-29, 400 cases of seed 123): 95.5 % and 78 %; with the memory and hazard of before issue 50's
    third pass, which ran five times longer than their options said, 81 % and 19 % (100 cases of seed 7: the dry
    rail's estimate held at the "flat curve at the demand" the patch's samples left).  A correct implementation at
    95.5 % (78 %) falls below 85 % (62 %) of 150 with probability < 1e-5."""
    seed = case_seed("rails that change")
    print("seed", seed)
    rng = np.random.default_rng(seed)
    hits = np.array([_covered(rng, _sequence(rng)) for _ in range(150)])
    print("coverage at the patch's end, back on the dry rail:", hits.mean(axis=0))
    assert hits[:, 0].sum() >= 0.85 * 150, hits.mean(axis=0)
    assert hits[:, 1].sum() >= 0.62 * 150, hits.mean(axis=0)


def test_the_estimates_options_are_set_from_a_scenario_and_checked_at_load():
    """``[identifier.options.peak_estimate]`` reaches the TCU's estimate; a misspelt key or a hazard shorter than
    an update is one line at load.  memory_s 1.5 and hazard_s 10 (what ``hil replay`` sets for a log recorded
    before the third pass of issue 50) give the per-update constants the estimate ran with then: exp(-period /
    0.3) and period / 2 per update, every fifth period."""
    import pytest

    from hil.config import load_scenario
    from hil.errors import ConfigError
    from identifier.tcu import TractionIdentifier

    from .test_control import WET

    old = {"identifier.options.peak_estimate.memory_s": 1.5, "identifier.options.peak_estimate.hazard_s": 10.0}
    settings = load_scenario(WET, {"control.law": "identified", **old}).identifier_settings()
    est = TractionIdentifier(settings, "gp", 1).estimator
    assert est._keep == pytest.approx(math.exp(-settings.period_s / 0.3), rel=1e-12)
    assert est._log_h == pytest.approx(math.log(settings.period_s / 2.0), rel=1e-12)
    assert TractionIdentifier(load_scenario(WET).identifier_settings(), "gp", 1).estimator._keep == \
        pytest.approx(math.exp(-5 * settings.period_s / 0.3), rel=1e-12)
    for bad in ({"identifier.options.peak_estimate.memroy_s": 1.0}, {"identifier.options.peak_estimate.hazard_s": 1e-4}):
        with pytest.raises(ConfigError) as e:
            load_scenario(WET, bad)
        assert "[identifier.options.peak_estimate]" in str(e.value) and "\n" not in str(e.value)
