"""The TCU's prior over fault curves, parameterised by what a controller needs.

A curve of the paper's form with two terms, ``mu(v) = l0 + l1 exp(t1 v) + l2 exp(t2 v)`` (v = creep
speed in km/h), is written here by five numbers phi:

    peak_mu          mu at the curve's maximum
    peak_creep_kmh   v_p, the creep speed of the maximum
    mu_at_zero       mu(0)
    shape_a          a = -t1 v_p  (> 0: small a decays steeply after the peak, large a gently)
    shape_r          r = t2 / t1  (> 1: the second, faster term)

and mapped to theta = (l0, l1, l2, t1, t2) by solving the peak's two conditions:

    t1 = -a / v_p,  t2 = r t1
    mu'(v_p) = 0          ->  l2 = -(l1 / r) exp((r - 1) a)
    mu(v_p) - mu(0) = peak_mu - mu_at_zero
                          ->  l1 = (peak_mu - mu_at_zero) / D,
                              D = (exp(-a) - 1) - (exp(-a) - exp((r - 1) a)) / r   (> 0 for a > 0, r > 1)
    l0 = mu_at_zero - l1 - l2

With l1 > 0 > l2 and t2 < t1 < 0 the derivative changes sign once, so v_p is the only maximum and
the curve rises monotonically from mu(0) to it.  Why this form: the two numbers a controller acts on
(peak mu and peak creep) are coordinates, so the prior is stated in them (a range a user can name for
their rail) and their intervals are quantiles of the particle cloud, with no peak search per particle.

The prior is a box, each coordinate uniform (``peak_creep_kmh``, ``shape_a`` and ``shape_r``
log-uniform).  Particles live in unconstrained coordinates u (a logit per box side), so moving them
(``identifier/strategies/bayes.py``) can never leave the prior's support.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: phi's coordinates, in order
NAMES = ("peak_mu", "peak_creep_kmh", "mu_at_zero", "shape_a", "shape_r")
#: the default prior box: the peak box of the fault-curve families of plant/families.py (peak mu
#: 0.05-0.25, peak creep 0.4-3 km/h, mu(0) 0-0.02); the shape covers post-peak decays from steep (mu at
#: 3 v_p below zero) to gentle (above 0.95 peak_mu).  A wider box confirms more rails (a posterior piled
#: against the prior's edge is never confirmed) but also more of them wrongly (docs/design/identification.md
#: gives the bench's figures): this box is the safer default
DEFAULT_BOX = {"peak_mu": (0.05, 0.25), "peak_creep_kmh": (0.4, 3.0), "mu_at_zero": (0.0, 0.02),
               "shape_a": (0.4, 2.5), "shape_r": (1.3, 4.0)}
LOG_SCALE = {"peak_mu": False, "peak_creep_kmh": True, "mu_at_zero": False, "shape_a": True, "shape_r": True}


def theta_from_phi(phi: np.ndarray) -> np.ndarray:
    """(..., 5) phi -> (..., 5) theta = (l0, l1, l2, t1, t2) (module docstring)."""
    phi = np.asarray(phi, float)
    mp, vp, m0, a, r = (phi[..., i] for i in range(5))
    t1 = -a / vp
    t2 = r * t1
    e_a = np.exp(-a)
    e_ra = np.exp((r - 1.0) * a)
    d = (e_a - 1.0) - (e_a - e_ra) / r
    l1 = (mp - m0) / d
    l2 = -(l1 / r) * e_ra
    return np.stack([m0 - l1 - l2, l1, l2, t1, t2], axis=-1)


def theta_from_phi_floats(phi) -> tuple[float, ...]:
    """``theta_from_phi`` for one curve, in Python floats (a handful of numpy calls on 5-element
    arrays cost more than the arithmetic: this runs on the TCU's sample)."""
    mp, vp, m0, a, r = (float(x) for x in phi)
    t1 = -a / vp
    e_a, e_ra = math.exp(-a), math.exp((r - 1.0) * a)
    l1 = (mp - m0) / ((e_a - 1.0) - (e_a - e_ra) / r)
    l2 = -(l1 / r) * e_ra
    return (m0 - l1 - l2, l1, l2, t1, r * t1)


@dataclass(frozen=True)
class CurvePrior:
    """A box prior over phi; ``box`` maps every name of ``NAMES`` to (low, high)."""

    box: dict

    @classmethod
    def from_options(cls, options: dict) -> "CurvePrior":
        """The default box with any of its sides given in ``options`` (e.g. ``peak_mu = [0.08, 0.2]``)."""
        box = dict(DEFAULT_BOX)
        for name in NAMES:
            if name in options:
                lo, hi = (float(x) for x in options[name])
                if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                    raise ValueError(f"prior {name}: need two finite numbers low < high, got {options[name]}")
                if LOG_SCALE[name] and lo <= 0:
                    raise ValueError(f"prior {name}: must be > 0, got {options[name]}")
                box[name] = (lo, hi)
        if box["mu_at_zero"][1] >= box["peak_mu"][0]:
            raise ValueError("prior: mu_at_zero must stay below peak_mu")
        if box["shape_r"][0] <= 1.0:
            raise ValueError("prior shape_r: must be > 1")
        return cls(box)

    def bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo = np.array([self.box[n][0] for n in NAMES])
        hi = np.array([self.box[n][1] for n in NAMES])
        log = np.array([LOG_SCALE[n] for n in NAMES])
        safe = lambda x: np.log(np.where(log, x, 1.0))      # noqa: E731  (log only where the scale is log)
        return np.where(log, safe(lo), lo), np.where(log, safe(hi), hi), log

    def phi_from_u(self, u: np.ndarray) -> np.ndarray:
        """Unconstrained (..., 5) -> phi inside the box: lo + (hi - lo) sigmoid(u) (on log scale where set)."""
        lo, hi, log = self.bounds()
        s = lo + (hi - lo) / (1.0 + np.exp(-np.asarray(u, float)))
        return np.where(log, np.exp(s), s)

    def phi_from_u_floats(self, u) -> list[float]:
        """``phi_from_u`` for one particle, in Python floats."""
        out = []
        for name, x in zip(NAMES, u):
            lo, hi = self.box[name]
            if LOG_SCALE[name]:
                lo, hi = math.log(lo), math.log(hi)
            s = lo + (hi - lo) / (1.0 + math.exp(-float(x)))
            out.append(math.exp(s) if LOG_SCALE[name] else s)
        return out

    def sample_u(self, n: int, rng) -> np.ndarray:
        """n draws from the prior, in u: logit of a uniform (so phi is uniform in its box side)."""
        p = rng.uniform(1e-9, 1.0 - 1e-9, size=(n, len(NAMES)))
        return np.log(p) - np.log1p(-p)

    def upper_peak_creep_kmh(self) -> float:
        """The highest peak creep the prior allows: past it the TCU knows it is in the serious stage."""
        return float(self.box["peak_creep_kmh"][1])
