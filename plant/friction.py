"""Friction (adhesion) characteristic curves: the paper's exponential form and Polach's creep-force law.

Exponential form (paper eq. 3), ``FrictionCurve``::

    mu(v_s) = lambda0 + sum_i lambda_i * exp(tau_i * v_s)

with the creep speed ``v_s`` in **km/h**.  Any number of exponential terms is allowed; the
paper's curves use two.

Polach's law (O. Polach, "Creep forces in simulations of traction vehicles running on adhesion
limit", Wear 258 (2005) 992-1000, longitudinal creep only), ``PolachCurve``::

    w   = |v_s| / 3.6                                   slip velocity, m/s
    s   = w / v_t                                       creepage (v_t: train speed, m/s)
    f   = mu_static * ((1 - A) * exp(-B * w) + A)       friction coefficient falling with slip velocity
    eps = stiffness * s / f                             gradient of the tangential stress
    mu  = (2 f / pi) * (k_A eps / (1 + (k_A eps)^2) + arctan(k_S eps))

``stiffness`` is Polach's (2/3) C pi a^2 b / Q lumped into one number (C: contact shear stiffness,
N/m^3; a, b: contact-ellipse semi-axes; Q: wheel load), so eps = stiffness * s / f is his eq. (3);
k_A and k_S (k_S <= k_A <= 1) are his reduction factors in the areas of adhesion and slip.  For small
creep mu ~ (2/pi) (k_A + k_S) stiffness * s.  Its mu depends on the train speed through the creepage.

Both classes are odd in the creep speed on CasADi symbols (``mu_casadi``), so braking creep brakes,
and evaluate on numpy arrays (identifier, metrics) and on CasADi symbols (plant), so the plant and the
truth used by the metrics cannot drift apart.  ``mu_casadi(creep_speed_kmh, train_speed_ms)`` is the
one interface the plants call; the exponential curve ignores the train speed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: creep-speed range (km/h) searched for a curve's peak; every curve of interest peaks well inside.
PEAK_SEARCH_KMH = (0.0, 30.0)
#: km/h per m/s (plant.params.KMH_PER_MS; repeated here so this module imports nothing of the project)
_KMH_PER_MS = 3.6
#: Polach's creepage divides by the train speed; below this (m/s) the law uses this instead (standstill)
MIN_TRAIN_SPEED_MS = 0.1


#: 1 / golden ratio, the golden-section search's step
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


def _golden_max(f, lo: float, hi: float, xtol: float) -> float:
    """The maximiser of ``f`` on [lo, hi] (unimodal there) to ``xtol``: golden-section search (Kiefer 1953),
    the bracket shrinking by 1/phi a step.  Plain Python rather than scipy.optimize: the plant computes a
    peak at import (plant.families), and importing scipy.optimize for it weighed on every plant process's
    start-up (docs/design/ci.md)."""
    a, b = lo, hi
    c, d = b - _INV_PHI * (b - a), a + _INV_PHI * (b - a)
    fc, fd = f(c), f(d)
    while b - a > xtol:
        if fc >= fd:                      # the maximum lies in [a, d]
            b, d, fd = d, c, fc
            c = b - _INV_PHI * (b - a)
            fc = f(c)
        else:                             # in [c, b]
            a, c, fc = c, d, fd
            d = a + _INV_PHI * (b - a)
            fd = f(d)
    return (a + b) / 2.0


def _bisect(g, lo: float, hi: float, xtol: float) -> float:
    """The root of ``g`` in [lo, hi] (signs differ at the ends) to ``xtol``, by bisection."""
    glo = g(lo)
    if glo == 0.0:
        return lo
    while hi - lo > xtol:
        mid = (lo + hi) / 2.0
        gm = g(mid)
        if gm == 0.0:
            return mid
        if (gm > 0.0) == (glo > 0.0):
            lo, glo = mid, gm
        else:
            hi = mid
    return (lo + hi) / 2.0


class _CurveShape:
    """Peak and stable-side inverse of any curve with a numpy ``mu(creep_speed_kmh)``."""

    name: str

    def peak(self) -> tuple[float, float]:
        """(creep speed in km/h, mu) at the curve's maximum in PEAK_SEARCH_KMH."""
        grid = np.linspace(*PEAK_SEARCH_KMH, 3001)
        i = int(np.argmax(self.mu(grid)))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        if hi <= lo:
            return float(grid[i]), float(self.mu(grid[i]))
        v = _golden_max(lambda x: float(self.mu(x)), float(lo), float(hi), 1e-9)
        return v, float(self.mu(v))

    def creep_for_mu(self, mu_target: float) -> float:
        """Creep speed (km/h) on the stable (rising) side where the curve reaches ``mu_target``."""
        v_peak, mu_peak = self.peak()
        mu0 = float(self.mu(0.0))
        if not (mu0 <= mu_target <= mu_peak):
            raise ValueError(f"curve {self.name!r}: mu {mu_target} is outside its stable range "
                             f"[{mu0:.4f}, {mu_peak:.4f}]")
        if mu_target == mu_peak:
            return v_peak
        return _bisect(lambda v: float(self.mu(v)) - mu_target, 0.0, v_peak, 1e-12)


@dataclass(frozen=True)
class FrictionCurve(_CurveShape):
    """mu(v_s) = lambda0 + sum(lambdas[i] * exp(taus[i] * v_s)), v_s in km/h; independent of the train speed."""

    model = "exp"

    lambda0: float
    lambdas: tuple[float, ...]
    taus: tuple[float, ...]
    name: str = ""

    def __post_init__(self):
        if len(self.lambdas) != len(self.taus):
            raise ValueError(f"curve {self.name!r}: {len(self.lambdas)} lambdas but {len(self.taus)} taus")
        if not self.lambdas:
            raise ValueError(f"curve {self.name!r}: needs at least one exponential term")

    @property
    def params(self) -> np.ndarray:
        """(lambda0, lambda1..n, tau1..n) as one vector."""
        return np.array([self.lambda0, *self.lambdas, *self.taus], dtype=float)

    @property
    def n_terms(self) -> int:
        return len(self.lambdas)

    # -- evaluation ------------------------------------------------------------------------
    def mu(self, creep_speed_kmh):
        """Friction coefficient at ``creep_speed_kmh`` (numpy array or scalar) on the traction side."""
        v = np.asarray(creep_speed_kmh, dtype=float)
        out = np.full(v.shape, self.lambda0, dtype=float)
        for lam, tau in zip(self.lambdas, self.taus):
            out = out + lam * np.exp(tau * v)
        return out

    def mu_at(self, creep_speed_kmh, train_speed_ms=None):
        """``mu`` (the train speed does not enter this form)."""
        return self.mu(creep_speed_kmh)

    def mu_casadi(self, creep_speed_kmh, train_speed_ms=None):
        """Same curve on a CasADi expression; odd-symmetric so that braking creep brakes.
        ``train_speed_ms`` is ignored (the interface every curve shares)."""
        import casadi as ca

        v = ca.fabs(creep_speed_kmh)
        mu = self.lambda0
        for lam, tau in zip(self.lambdas, self.taus):
            mu = mu + lam * ca.exp(tau * v)
        return ca.sign(creep_speed_kmh) * mu


def polach_mu(creep_speed_kmh, train_speed_ms, mu_static, A, B_s_per_m, k_A, k_S, stiffness):
    """Polach's law on numpy arrays (broadcast together), odd in the creep speed: the module docstring's
    equations.  The families' vectorised sampler (plant/families.py) and ``PolachCurve`` both use it."""
    v = np.asarray(creep_speed_kmh, dtype=float)
    w = np.abs(v) / _KMH_PER_MS
    f = mu_static * ((1.0 - A) * np.exp(-B_s_per_m * w) + A)
    eps = stiffness * (w / np.maximum(train_speed_ms, MIN_TRAIN_SPEED_MS)) / f
    ka = k_A * eps
    return np.sign(v) * (2.0 / math.pi) * f * (ka / (1.0 + ka * ka) + np.arctan(k_S * eps))


@dataclass(frozen=True)
class PolachCurve(_CurveShape):
    """Polach's creep-force law (module docstring) as a friction curve mu(v_s, v_t), v_s in km/h.

    ``mu_casadi(v_s, v_t)`` (the plant) uses the train speed the plant integrates.  The curve's *truth*
    (``mu(v_s)``, ``peak()``, ``creep_for_mu``) is taken at ``reference_train_speed_ms``: the scenario
    loader (hil/config.py) sets it to the train speed at the fault time (``plant.model.
    train_speed_before_fault``), unless the scenario names it.  Not the initial train speed: the train
    accelerates by about 0.8 m/s^2 before the fault in the paper's scenarios, 4 % of 10 m/s by t_f =
    0.5 s, and the peak creep speed moves with it (eps scales with 1/v_t).  During the early stage
    (tens of ms) the train speed changes by well under 1 %, so the peak the plant's wheelset meets is
    this one to within that.

    Parameters, with Polach's recommended orders of magnitude: ``mu_static`` (mu_0, > 0), ``A`` (ratio
    of the friction at infinite slip velocity to mu_0, 0 < A <= 1), ``B_s_per_m`` (friction decrease
    rate, s/m, >= 0), ``k_A``, ``k_S`` (0 < k_S <= k_A <= 1) and ``stiffness`` ((2/3) C pi a^2 b / Q,
    dimensionless, > 0).  mu(0) = 0: a wheel that does not slip transmits no creep force.
    No ``params`` vector: the identifier's exponential form does not hold this law.
    """

    mu_static: float
    A: float
    B_s_per_m: float
    k_A: float
    k_S: float
    stiffness: float
    reference_train_speed_ms: float
    name: str = ""

    model = "polach"
    #: the scenario keys (hil/config.py), in this order; reference_train_speed_ms is optional there
    KEYS = ("mu_static", "A", "B_s_per_m", "k_A", "k_S", "stiffness", "reference_train_speed_ms")

    def __post_init__(self):
        problems = []
        if not self.mu_static > 0:
            problems.append(f"mu_static must be > 0, got {self.mu_static!r}")
        if not 0 < self.A <= 1:
            problems.append(f"A must be in (0, 1], got {self.A!r}")
        if not self.B_s_per_m >= 0:
            problems.append(f"B_s_per_m must be >= 0, got {self.B_s_per_m!r}")
        if not 0 < self.k_S <= self.k_A <= 1:
            problems.append(f"k_S and k_A must satisfy 0 < k_S <= k_A <= 1, got k_S={self.k_S!r}, k_A={self.k_A!r}")
        if not self.stiffness > 0:
            problems.append(f"stiffness must be > 0, got {self.stiffness!r}")
        if not self.reference_train_speed_ms > 0:
            problems.append(f"reference_train_speed_ms must be > 0, got {self.reference_train_speed_ms!r}")
        if problems:
            raise ValueError(f"curve {self.name!r}: " + "; ".join(problems))

    @property
    def values(self) -> dict[str, float]:
        """The law's parameters by scenario key (``KEYS``)."""
        return {k: float(getattr(self, k)) for k in self.KEYS}

    def at_train_speed(self, train_speed_ms: float) -> "PolachCurve":
        """The same mu(v_s) curve with its truth taken at another train speed: the stiffness scales with
        the speed (eps depends on stiffness / v_t only), so ``mu(v_s)`` and ``peak()`` are unchanged."""
        scale = train_speed_ms / self.reference_train_speed_ms
        return PolachCurve(self.mu_static, self.A, self.B_s_per_m, self.k_A, self.k_S, self.stiffness * scale,
                           train_speed_ms, self.name)

    # -- evaluation ------------------------------------------------------------------------
    def mu_at(self, creep_speed_kmh, train_speed_ms):
        """mu at ``creep_speed_kmh`` (numpy array or scalar) and the train speed ``train_speed_ms``."""
        return polach_mu(creep_speed_kmh, train_speed_ms, self.mu_static, self.A, self.B_s_per_m, self.k_A,
                         self.k_S, self.stiffness)

    def mu(self, creep_speed_kmh):
        """mu at ``creep_speed_kmh`` at the reference train speed (the truth; odd in the creep speed)."""
        return self.mu_at(creep_speed_kmh, self.reference_train_speed_ms)

    def mu_casadi(self, creep_speed_kmh, train_speed_ms=None):
        """The law on CasADi expressions, odd in the creep speed; ``train_speed_ms`` None: the reference."""
        import casadi as ca

        v_t = self.reference_train_speed_ms if train_speed_ms is None else train_speed_ms
        w = ca.fabs(creep_speed_kmh) / _KMH_PER_MS
        f = self.mu_static * ((1.0 - self.A) * ca.exp(-self.B_s_per_m * w) + self.A)
        eps = self.stiffness * (w / ca.fmax(v_t, MIN_TRAIN_SPEED_MS)) / f
        ka = self.k_A * eps
        return ca.sign(creep_speed_kmh) * (2.0 / math.pi) * f * (ka / (1.0 + ka * ka) + ca.atan(self.k_S * eps))
