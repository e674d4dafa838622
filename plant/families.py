"""Families of fault curves: a documented, seeded generator of fault scenarios for honest benchmarks.

The identifier assumes the paper's exponential form; a benchmark that only ever shows it FFCC-a and
FFCC-b (or curves of its own form) flatters it.  A *family* is a probability distribution over fault
curves plus a rule that picks, for each curve, the demanded adhesion ``mu_required`` so that the fault
makes the wheelset slip with a deterioration time in a set band.

Families (``FAMILIES``)
-----------------------
``exp``      the paper's form with n = 2 terms, mu(v) = lambda0 + lambda1 e^(tau1 v) + lambda2 e^(tau2 v).
``polach``   Polach's creep-force law (plant/friction.py ``PolachCurve``), a form the identifier does not
             assume.
``default``  each curve is ``exp`` or ``polach`` with probability 1/2: a fair coin, the first number of
             the curve's random stream.

Every family draws, for each curve (v in km/h, the creep speed; all at the train speed at the fault):

* peak mu ``mu_p`` uniform in ``PEAK_MU`` = [0.05, 0.25] and peak creep speed ``v_p`` log-uniform in
  ``PEAK_CREEP_KMH`` = [0.4, 3] km/h, jointly restricted (by rejection, a curve-only rule) to
  ``mu_p <= HEADROOM * N(min(v_p, v_N))`` where N is the reference dry-rail NFCC-0 of method.md,
  (lambda0, lambda1, lambda2, tau1, tau2) = (0, 1, -1, -0.54, -1.2), v_N = 1.2 km/h its peak creep
  and HEADROOM = 0.9: a fault makes the rail worse, and a mu_required between the fault peak and
  NFCC-0 must exist on NFCC-0's stable side below the fault's peak creep (else the wheelset is past the
  fault peak at the fault: no early stage).  The rule removes the corner v_p < 0.95 km/h with high mu_p
  (7.7 % of the box); the joint density is uniform x log-uniform on what is left.
* the shape:

  ``exp``     mu(0) = mu_0 uniform in [0, 0.02]; the asymptote ratio q = lambda0 / mu_p uniform in
              [0, 0.7] (0: mu falls towards 0 as the paper's curves do, steep; 0.7: keeps 70 % of its
              peak, gentle) and the term ratio rho = tau2 / tau1 log-uniform in [1.5, 4].  Writing
              x = -tau1 v_p, y = rho x, the peak at v_p (mu'(v_p) = 0), mu(v_p) = mu_p and mu(0) = mu_0
              give lambda2 = -lambda1 (x/y) e^(y-x), lambda1 = (mu_p - mu_0) / D(x),
              D = e^-x (1 - x/y) - 1 + (x/y) e^(y-x) > 0, lambda0 = mu_p - lambda1 e^-x (1 - x/y); x then
              solves lambda0 = q mu_p (one root: lambda0 / mu_p rises monotonically from -inf to 1 with x).
              mu'(v) = lambda1 x/v_p e^(-x v/v_p) (e^((y-x)(1 - v/v_p)) - 1): positive below v_p, negative
              above, so every curve rises monotonically to its one peak at v_p and falls after it.
              The drawn curves keep tau in about [-6.8, -0.13] /(km/h), |lambda_i| < 1.7 and
              lambda0 in [0, 0.175] (inside the identifier's box: |lambda_i| <= 5, tau in [-10, -0.001]).
              mu(3 v_p) / mu_p spans about 0.42-0.81 (FFCC-a: 0.43).
  ``polach``  mu(0) = 0 (the law's); A uniform in [0.1, 0.6]; b = B w_p log-uniform in [0.05, 1] (B the
              friction decrease rate in s/m, w_p = v_p / 3.6 the peak slip velocity: b is how much of
              the friction decrease has happened at the peak); k_A uniform in [0.3, 1] and
              k_S = r k_A with r uniform in [0.5, 1] (Polach: k_S <= k_A <= 1; r >= 0.5 keeps the
              adhesion term monotone).  With u = w / w_p, h(u) = (1 - A) e^(-b u) + A and
              E = k u / h(u), mu = (2/pi) mu_static h(u) (E / (1 + E^2) + arctan(r E)); the
              dimensionless stiffness k solves d mu / du = 0 at u = 1 (one root, by bisection in log k),
              then mu_static = (pi/2) mu_p / (h(1) (E(1)/(1+E(1)^2) + arctan(r E(1)))), B = b / w_p and
              the law's stiffness = k v_t mu_static / (k_A w_p) at the train speed v_t.  Every curve of
              these ranges rises monotonically to its peak at v_p, and the peak is global up to
              75 v_p (checked on 200 000 draws; tests/test_families.py checks fresh ones); far past the
              peak the law's mu recovers slightly towards A mu_static (< mu_p) as arctan saturates.
              mu(3 v_p) / mu_p spans about 0.44-0.98; mu_static 0.05-0.9, stiffness 1-1000 at 10 m/s
              (peak creepages of 1-8 % at 10 m/s: a wet or contaminated rail's low stiffness, well
              below dry-rail values).

The curve depends on nothing else: not on the base scenario, not on mu_required, not on T_det.
``sample_curves(family, n, rng, train_speed_ms)`` draws n curves from exactly this distribution,
vectorised (an offline Bayesian oracle's prior); ``draw`` calls it with n = 1 on the draw's own stream
``draw_rng(family, seed, index) = np.random.default_rng([seed, index, FAMILY_TAG[family]])``, so one
implementation maps random numbers to curves.  A Polach curve's mu(v_s) at the train speed it was
drawn for does not depend on that speed (the stiffness scales with it: ``PolachCurve.at_train_speed``).

mu_required and the deterioration time
--------------------------------------
After the curve, the draw's stream gives one more number z uniform in [0, 1): the target deterioration
time T* = T_lo (T_hi / T_lo)^z, log-uniform in [T_lo, T_hi] with (T_lo, T_hi) = ``TDET_S`` = (20, 150) ms,
unless the curve cannot slip that fast from any admissible mu_required (possible only for v_p above
NFCC-0's peak creep and high mu_p; about 5 % of curves on ffcc_a's base, up to ~56 ms): then T_lo is
the fastest it can (at mu_required = NFCC-0's peak), always below T_hi on ffcc_a's base.  Likewise T_hi
is the slowest it can when that is below 150 ms: a curve whose peak creep is low reaches it within a
bounded time even from mu_required just above its peak (``MIN_EXCESS_LOG10``).
T_det runs from the fault until the creep first reaches the fault curve's peak creep (plant.stages).
mu_required then solves T_det(mu_required) = T* on (mu_p, N_base(min(v_p, v_Nbase))): above the fault
peak so the wheelset slips, and below NFCC-0 at the fault's peak creep (on NFCC-0's stable side, so the
scenario's equilibrium exists and starts below the peak creep).  T_det(mu_required) comes from the
wheelset's early stage integrated exactly as the plant integrates it (``predict_t_det``):

    J_eq dw_m/dt = T_e - c mu(v_s, v_t),        c = torque_per_mu_nm
    M dv_t/dt    = mu T_W g + (n_driven - 1) mu_required T_W g - R(v_t)

with T_e the TCU's torque demand, which is the equilibrium torque of plant.model.equilibrium held for
the whole run (hil/config.py Scenario.identifier_settings: torque_demand_nm; identifier/tcu.py commands
it every period): T_e = mu_required c + J_eq (R_g / r) a_0, a_0 = (n_driven mu_required T_W g - R(v_0)) / M.
The state at the fault: v_t from plant.model.train_speed_before_fault, v_s at NFCC-0's creep for
mu_required (the plant holds it; it drifts by ~1e-5 km/h as the resistance grows).  RK4 at 0.25 ms
(the plant uses 0.1 ms); the plant's tracker sees the crossing at the first exchange period after it,
so the simulated T_det is the predicted one rounded up to the period (1 ms), give or take the
prediction's own error (under one 0.25 ms prediction step: the plant steps at 0.1 ms and its held creep
drifts).

The base scenario (vehicle, NFCC-0, initial train speed, fault time) enters mu_required and the
Polach stiffness only; ``draw`` defaults to ffcc_a's (``DEFAULT_BASE``), ``draw_scenario_text`` uses
the base text it is given.  A base whose NFCC-0 is weaker than the reference may leave a curve no
admissible mu_required: ``draw`` then raises ValueError naming the draw.
"""
from __future__ import annotations

import json
import math
import re
import tomllib
from dataclasses import dataclass, field

import numpy as np

from .friction import FrictionCurve, PolachCurve, polach_mu
from .model import train_speed_before_fault
from .params import KMH_PER_MS, WheelsetParams

FAMILIES = {
    "exp": "the paper's exponential form, n = 2 terms",
    "polach": "Polach's creep-force law (plant/friction.py PolachCurve)",
    "default": "exp or polach, each with probability 1/2 (a fair coin per curve)",
}
#: the third entry of every draw's seed sequence, one per family
FAMILY_TAG = {"exp": 1, "polach": 2, "default": 3}

PEAK_MU = (0.05, 0.25)                   # uniform
PEAK_CREEP_KMH = (0.4, 3.0)              # log-uniform
HEADROOM = 0.9                           # mu_p <= HEADROOM * N(min(v_p, v_N))
#: method.md's dry-rail NFCC-0, the reference of the joint peak rule (the shipped scenarios use it too)
REFERENCE_NORMAL = FrictionCurve(0.0, (1.0, -1.0), (-0.54, -1.2), "NFCC-0 (method.md)")
TDET_S = (0.020, 0.150)                  # target deterioration time, log-uniform
EXP_MU0 = (0.0, 0.02)                    # uniform
EXP_ASYMPTOTE_RATIO = (0.0, 0.7)         # q = lambda0 / mu_p, uniform
EXP_TERM_RATIO = (1.5, 4.0)              # rho = tau2 / tau1, log-uniform
POLACH_A = (0.1, 0.6)                    # uniform
POLACH_B_AT_PEAK = (0.05, 1.0)           # b = B * w_p, log-uniform
POLACH_K_A = (0.3, 1.0)                  # uniform
POLACH_KS_RATIO = (0.5, 1.0)             # k_S / k_A, uniform
#: RK4 step of the T_det prediction (s) and how far past the band it integrates
PREDICT_STEP_S = 2.5e-4
PREDICT_HORIZON_S = 0.2

LAW_EXP, LAW_POLACH = 0, 1


_REF_PEAK_KMH, _REF_PEAK_MU = REFERENCE_NORMAL.peak()


def peak_mu_cap(peak_creep_kmh):
    """The joint rule's ceiling on the peak mu at this peak creep speed (km/h): HEADROOM * N(min(v_p, v_N))."""
    v = np.minimum(np.asarray(peak_creep_kmh, float), _REF_PEAK_KMH)
    return HEADROOM * REFERENCE_NORMAL.mu(v)


# -- the shapes ----------------------------------------------------------------------------------------
def _exp_d(x, rho):
    return np.exp(-x) * (1 - 1 / rho) - 1 + (1 / rho) * np.exp((rho - 1) * x)


def _exp_asymptote_ratio(x, rho, mu0_ratio):
    """lambda0 / mu_p as a function of x = -tau1 v_p (rises monotonically from -inf to 1)."""
    return 1 - (1 - mu0_ratio) * np.exp(-x) * (1 - 1 / rho) / _exp_d(x, rho)


def exp_coefficients(peak_mu, peak_creep_kmh, mu0, asymptote_ratio, term_ratio):
    """(lambda0, lambda1, lambda2, tau1, tau2) arrays of the exp curves with these peaks, mu(0), lambda0 / mu_p
    and tau2 / tau1 (module docstring).  Vectorised; x by 80 bisections in log x on [1e-3, 50]."""
    mp, vp, m0, q, rho = (np.asarray(a, float) for a in (peak_mu, peak_creep_kmh, mu0, asymptote_ratio, term_ratio))
    lo = np.full(np.broadcast(mp, q).shape, math.log(1e-3))
    hi = np.full_like(lo, math.log(50.0))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        above = _exp_asymptote_ratio(np.exp(mid), rho, m0 / mp) > q
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    x = np.exp(0.5 * (lo + hi))
    y = rho * x
    lam1 = (mp - m0) / _exp_d(x, rho)
    lam0 = mp - lam1 * np.exp(-x) * (1 - x / y)
    lam2 = -lam1 * (x / y) * np.exp(y - x)
    return lam0, lam1, lam2, -x / vp, -y / vp


def _polach_h(u, A, b):
    return (1 - A) * np.exp(-b * u) + A


def _polach_shape(u, A, b, r, k):
    """mu / ((2/pi) mu_static) at u = w / w_p."""
    h = _polach_h(u, A, b)
    e = k * u / h
    return h * (e / (1 + e * e) + np.arctan(r * e))


def _polach_slope_at_peak(A, b, r, k):
    """d/du of ``_polach_shape`` at u = 1 (analytic)."""
    h = _polach_h(1.0, A, b)
    dh = -b * (1 - A) * np.exp(-b)
    e = k / h
    de = k * (h - dh) / (h * h)
    g = e / (1 + e * e) + np.arctan(r * e)
    dg = (1 - e * e) / (1 + e * e) ** 2 + r / (1 + r * r * e * e)
    return dh * g + h * dg * de


def polach_parameters(peak_mu, peak_creep_kmh, A, b, k_A, ks_ratio, train_speed_ms):
    """(mu_static, A, B_s_per_m, k_A, k_S, stiffness) arrays of the Polach curves that peak at (v_p, mu_p) at
    ``train_speed_ms``, given the shape numbers (module docstring).  Vectorised; k by 100 bisections in log k."""
    mp, vp, A, b, k_A, r = (np.asarray(a, float) for a in (peak_mu, peak_creep_kmh, A, b, k_A, ks_ratio))
    lo = np.full(np.broadcast(mp, A).shape, math.log(1e-4))
    hi = np.full_like(lo, math.log(1e4))
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        rising = _polach_slope_at_peak(A, b, r, np.exp(mid)) > 0
        lo = np.where(rising, mid, lo)
        hi = np.where(rising, hi, mid)
    k = np.exp(0.5 * (lo + hi))
    w_p = vp / KMH_PER_MS
    mu_static = (math.pi / 2) * mp / _polach_shape(1.0, A, b, r, k)
    stiffness = k * train_speed_ms * mu_static / (k_A * w_p)
    return mu_static, A, b / w_p, k_A, r * k_A, stiffness


# -- the batch -----------------------------------------------------------------------------------------------
@dataclass
class CurveBatch:
    """n curves of one family, evaluated together.  Rows with ``law == LAW_EXP`` use ``exp_params``
    (lambda0, lambda1, lambda2, tau1, tau2), the others ``polach_params`` (mu_static, A, B_s_per_m, k_A, k_S,
    stiffness at ``train_speed_ms``); the unused block of a row is NaN.  ``shape``: the drawn shape numbers
    by name (NaN where they do not apply)."""

    family: str
    train_speed_ms: float
    law: np.ndarray                 # (n,) LAW_EXP or LAW_POLACH
    peak_mu: np.ndarray             # (n,)
    peak_creep_kmh: np.ndarray      # (n,)
    mu0: np.ndarray                 # (n,) mu at zero creep
    exp_params: np.ndarray          # (n, 5)
    polach_params: np.ndarray       # (n, 6)
    shape: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.law.shape[0])

    def mu(self, creep_speed_kmh) -> np.ndarray:
        """(n, S) friction coefficients at the creep speeds (km/h; a (S,) grid, or (n, S) per curve), each
        curve at ``train_speed_ms``; row i equals ``self.curve(i).mu(creep_speed_kmh)``."""
        v = np.asarray(creep_speed_kmh, float)
        v = np.broadcast_to(v if v.ndim == 2 else v.reshape(1, -1), (len(self), v.shape[-1]))
        out = np.empty(v.shape)
        e = self.law == LAW_EXP
        if e.any():
            l0, l1, l2, t1, t2 = (self.exp_params[e, j, None] for j in range(5))
            ve = v[e]
            out[e] = l0 + l1 * np.exp(t1 * ve) + l2 * np.exp(t2 * ve)
        p = ~e
        if p.any():
            ms, A, B, ka, ks, c = (self.polach_params[p, j, None] for j in range(6))
            out[p] = polach_mu(v[p], self.train_speed_ms, ms, A, B, ka, ks, c)
        return out

    def curve(self, i: int, name: str = "fault") -> FrictionCurve | PolachCurve:
        """Row i as the plant's curve object (a PolachCurve's truth at ``train_speed_ms``)."""
        if self.law[i] == LAW_EXP:
            l0, l1, l2, t1, t2 = (float(x) for x in self.exp_params[i])
            return FrictionCurve(l0, (l1, l2), (t1, t2), name)
        ms, A, B, ka, ks, c = (float(x) for x in self.polach_params[i])
        return PolachCurve(ms, A, B, ka, ks, c, float(self.train_speed_ms), name)


#: each law's curve coordinates in the order they are drawn: (name, (low, high), log-uniform?); a curve
#: is a point z of the unit cube, each coordinate mapped onto its range (``from_unit``), restricted by
#: the joint peak rule (``peak_allowed``)
LATENT = {
    LAW_EXP: (("peak_mu", PEAK_MU, False), ("peak_creep_kmh", PEAK_CREEP_KMH, True), ("mu0", EXP_MU0, False),
              ("asymptote_ratio", EXP_ASYMPTOTE_RATIO, False), ("term_ratio", EXP_TERM_RATIO, True)),
    LAW_POLACH: (("peak_mu", PEAK_MU, False), ("peak_creep_kmh", PEAK_CREEP_KMH, True), ("A", POLACH_A, False),
                 ("b_at_peak", POLACH_B_AT_PEAK, True), ("k_A", POLACH_K_A, False),
                 ("ks_ratio", POLACH_KS_RATIO, False)),
}


def from_unit(z, lo_hi, log: bool):
    """A coordinate's value from its unit-interval number: uniform, or log-uniform, on ``lo_hi``."""
    lo, hi = lo_hi
    if log:
        return np.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * z)
    return lo + (hi - lo) * z


def peak_allowed(z_peak_mu, z_peak_creep):
    """The joint peak rule on unit numbers (module docstring)."""
    return from_unit(z_peak_mu, PEAK_MU, False) <= peak_mu_cap(from_unit(z_peak_creep, PEAK_CREEP_KMH, True))


def _peaks(rng, n):
    """Unit numbers of (mu_p, v_p) for n curves, restricted to the joint peak rule by rejection."""
    zm, zv = np.empty(n), np.empty(n)
    todo = np.arange(n)
    while todo.size:
        m = rng.random(todo.size)
        v = rng.random(todo.size)
        ok = peak_allowed(m, v)
        zm[todo[ok]], zv[todo[ok]] = m[ok], v[ok]
        todo = todo[~ok]
    return zm, zv


def latent_values(law: int, z: np.ndarray) -> list[np.ndarray]:
    """The coordinates' values from unit numbers z (n, d)."""
    return [from_unit(z[:, i], lo_hi, log) for i, (_, lo_hi, log) in enumerate(LATENT[law])]


def curves_of_law(law: int, z: np.ndarray, train_speed_ms: float):
    """(peak_mu, peak_creep_kmh, mu0, exp_params, polach_params, shape) of the curves at unit numbers z."""
    n = z.shape[0]
    nan5, nan6 = np.full((n, 5), np.nan), np.full((n, 6), np.nan)
    if law == LAW_EXP:
        mp, vp, mu0, q, rho = latent_values(law, z)
        ep = np.column_stack(exp_coefficients(mp, vp, mu0, q, rho))
        return mp, vp, mu0, ep, nan6, {"asymptote_ratio": q, "term_ratio": rho}
    mp, vp, A, b, k_A, r = latent_values(law, z)
    pp = np.column_stack(polach_parameters(mp, vp, A, b, k_A, r, train_speed_ms))
    return mp, vp, np.zeros(n), nan5, pp, {"A": A, "b_at_peak": b, "k_A": k_A, "ks_ratio": r}


def unit_points(law: int, n: int, rng) -> np.ndarray:
    """n curves of one law as unit numbers z (n, d): the family's prior in its unit cube (uniform under
    the joint peak rule); ``curves_of_law`` maps them to curves."""
    zm, zv = _peaks(rng, n)
    rest = [rng.random(n) for _ in LATENT[law][2:]]
    return np.column_stack([zm, zv, *rest])


def _sample_law(law: int, n: int, rng, train_speed_ms: float):
    """(peak_mu, peak_creep_kmh, mu0, exp_params, polach_params, shape) for n curves of one law."""
    return curves_of_law(law, unit_points(law, n, rng), train_speed_ms)


def batch_of_law(family: str, law: int, z: np.ndarray, train_speed_ms: float) -> "CurveBatch":
    """The curves at unit numbers z (n, d) of one law, as a batch (the oracle moves curves in z)."""
    mp, vp, mu0, ep, pp, shape = curves_of_law(law, z, train_speed_ms)
    full = {k: np.full(z.shape[0], np.nan) for k in SHAPE_KEYS}
    full.update(shape)
    return CurveBatch(family, float(train_speed_ms), np.full(z.shape[0], law), mp, vp, mu0, ep, pp, full)


SHAPE_KEYS = ("asymptote_ratio", "term_ratio", "A", "b_at_peak", "k_A", "ks_ratio")


def sample_curves(family: str, n: int, rng: np.random.Generator, train_speed_ms: float) -> CurveBatch:
    """n curves from ``family``'s curve distribution (module docstring), the Polach ones with their
    stiffness for ``train_speed_ms`` (their mu(v_s) at that speed does not depend on it).

    Stream order: (``default`` only) n coins, then the exp curves' numbers, then the Polach curves'.
    ``draw`` calls this with n = 1 on the draw's own stream."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
    if family == "exp":
        law = np.full(n, LAW_EXP)
    elif family == "polach":
        law = np.full(n, LAW_POLACH)
    else:
        law = np.where(rng.random(n) < 0.5, LAW_EXP, LAW_POLACH)
    mp, vp, mu0 = np.empty(n), np.empty(n), np.empty(n)
    ep, pp = np.full((n, 5), np.nan), np.full((n, 6), np.nan)
    shape = {k: np.full(n, np.nan) for k in SHAPE_KEYS}
    for which in (LAW_EXP, LAW_POLACH):
        rows = np.flatnonzero(law == which)
        if not rows.size:
            continue
        a, b, c, e, p, s = _sample_law(which, rows.size, rng, train_speed_ms)
        mp[rows], vp[rows], mu0[rows], ep[rows], pp[rows] = a, b, c, e, p
        for k, v in s.items():
            shape[k][rows] = v
    return CurveBatch(family, float(train_speed_ms), law, mp, vp, mu0, ep, pp, shape)


# -- the base scenario and the deterioration time --------------------------------------------------------------
@dataclass(frozen=True)
class Base:
    """What of the base scenario a draw needs: vehicle, NFCC-0, train speed at the start, fault time."""

    vehicle: WheelsetParams
    normal_curve: FrictionCurve
    initial_train_speed_ms: float
    fault_time_s: float
    name: str = "base"

    @classmethod
    def from_text(cls, text: str) -> "Base":
        """From a scenario's TOML text (its checks are hil.config.parse_scenario's; here only what is used)."""
        data = tomllib.loads(text)
        vehicle = WheelsetParams(**data.get("vehicle", {}))
        n = data["curves"]["normal"]
        if n.get("model", "exp") != "exp":
            raise ValueError("the base scenario's [curves.normal] must be exponential")
        normal = FrictionCurve(float(n["lambda0"]), tuple(float(x) for x in n["lambdas"]),
                               tuple(float(x) for x in n["taus"]), "normal")
        run = data["run"]
        return cls(vehicle, normal, float(run["initial_train_speed_ms"]), float(run["fault_time_s"]),
                   str(data.get("name", "base")))


#: scenarios/ffcc_a.toml's vehicle, NFCC-0, initial train speed and fault time
DEFAULT_BASE = Base(WheelsetParams(), FrictionCurve(0.0, (1.0, -1.0), (-0.54, -1.2), "normal"), 10.0, 0.5, "ffcc_a")


def _creep_for_mu(normal: FrictionCurve, mu_required: np.ndarray) -> np.ndarray:
    """NFCC-0's stable-side creep (km/h) for each mu_required (vectorised bisection to 1e-13 km/h)."""
    v_peak, _ = normal.peak()
    lo = np.zeros_like(mu_required)
    hi = np.full_like(mu_required, v_peak)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = normal.mu(mid) < mu_required
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def predict_t_det(base: Base, curve, mu_required, peak_creep_kmh: float,
                  horizon_s: float = PREDICT_HORIZON_S) -> np.ndarray:
    """T_det (s) for each mu_required (array): the early stage integrated from the fault as the plant does
    (module docstring); inf when the creep does not reach ``peak_creep_kmh`` within ``horizon_s``.

    ``curve``: the fault curve (its mu(v_s, v_t) via ``mu_at``); a PolachCurve is taken with its stiffness
    scaled to each mu_required's train speed at the fault (``at_train_speed``), as the draw's curve is."""
    p = base.vehicle
    mu_req = np.atleast_1d(np.asarray(mu_required, float))
    c = p.torque_per_mu_nm
    n_force = p.normal_force_n
    j_eq = p.equivalent_inertia_kgm2
    v0 = base.initial_train_speed_ms
    accel0 = (p.driven_axles * mu_req * n_force - p.running_resistance_n(v0)) / p.train_mass_kg
    torque = mu_req * c + j_eq * p.gear_ratio / p.wheel_radius_m * accel0
    v_f = train_speed_before_fault(p, mu_req, v0, base.fault_time_s)
    v_s0 = _creep_for_mu(base.normal_curve, mu_req)
    omega = (v_f + v_s0 / KMH_PER_MS) * p.gear_ratio / p.wheel_radius_m
    v_t = v_f.copy()
    others = (p.driven_axles - 1) * mu_req * n_force
    if isinstance(curve, PolachCurve):
        c0 = curve.stiffness / curve.reference_train_speed_ms
        params = (curve.mu_static, curve.A, curve.B_s_per_m, curve.k_A, curve.k_S, c0 * v_f)

        def mu_of(v_s, v_t_):
            return polach_mu(v_s, v_t_, *params)
    else:
        def mu_of(v_s, v_t_):
            return curve.mu(v_s)

    def rhs(om, vt):
        v_s = KMH_PER_MS * (om / p.gear_ratio * p.wheel_radius_m - vt)
        mu = mu_of(v_s, vt)
        return (torque - mu * c) / j_eq, (mu * n_force + others - p.running_resistance_n(vt)) / p.train_mass_kg

    def creep(om, vt):
        return KMH_PER_MS * (om / p.gear_ratio * p.wheel_radius_m - vt)

    h = PREDICT_STEP_S
    out = np.full(mu_req.shape, np.inf)
    prev = creep(omega, v_t)
    out[prev >= peak_creep_kmh] = 0.0
    t = 0.0
    for _ in range(int(math.ceil(horizon_s / h))):
        a1, b1 = rhs(omega, v_t)
        a2, b2 = rhs(omega + h / 2 * a1, v_t + h / 2 * b1)
        a3, b3 = rhs(omega + h / 2 * a2, v_t + h / 2 * b2)
        a4, b4 = rhs(omega + h * a3, v_t + h * b3)
        omega = omega + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        v_t = v_t + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
        t += h
        now = creep(omega, v_t)
        crossed = np.isinf(out) & (now >= peak_creep_kmh)
        if crossed.any():
            frac = (peak_creep_kmh - prev[crossed]) / (now[crossed] - prev[crossed])
            out[crossed] = t - h + h * frac
        if not np.isinf(out).any():
            break
        prev = now
    return out


#: the smallest excess of mu_required over the fault's peak searched, log10 of its fraction of the admissible range
MIN_EXCESS_LOG10 = -7.0


def _mu_required_range(base: Base, peak_mu: float, peak_creep_kmh: float) -> tuple[float, float]:
    """(lo, hi): mu_required above the fault peak, below NFCC-0 at min(peak creep, NFCC-0's peak creep)."""
    v_np, mu_np = base.normal_curve.peak()
    hi = float(base.normal_curve.mu(min(peak_creep_kmh, v_np))) if peak_creep_kmh < v_np else mu_np
    return peak_mu, hi * (1 - 1e-9)


def solve_mu_required(base: Base, curve, peak_mu: float, peak_creep_kmh: float, target_s: float,
                      rounds: int = 4, points: int = 16) -> float:
    """The mu_required whose predicted T_det is ``target_s``: ``rounds`` of ``points`` candidates each,
    log-spaced in mu_required - peak_mu, narrowing the bracket, then log-log interpolation."""
    lo, hi = _mu_required_range(base, peak_mu, peak_creep_kmh)
    span = hi - lo
    z_lo, z_hi = MIN_EXCESS_LOG10, 0.0     # log10 of (mu_required - peak_mu) / span
    for _ in range(rounds):
        zs = np.linspace(z_lo, z_hi, points)
        ts = predict_t_det(base, curve, lo + span * 10 ** zs, peak_creep_kmh)
        above = ts > target_s              # T falls as mu_required rises
        j = int(np.flatnonzero(above)[-1]) if above.any() else 0
        if j >= points - 1:
            return float(lo + span * 10 ** zs[-1])
        z_lo, z_hi = zs[j], zs[j + 1]
        t_lo, t_hi = ts[j], ts[j + 1]
    if not math.isfinite(t_lo) or t_hi <= 0:
        z = 0.5 * (z_lo + z_hi)
    else:
        z = z_lo + (z_hi - z_lo) * (math.log(target_s) - math.log(t_lo)) / (math.log(t_hi) - math.log(t_lo))
    z = min(max(z, MIN_EXCESS_LOG10), 0.0)      # never at the peak itself (the wheelset must slip)
    return float(lo + span * 10 ** z)


# -- a draw ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Draw:
    """One fault scenario of a family: the curve, mu_required and the deterioration time it was chosen for."""

    family: str                 # the family asked for (exp, polach, default)
    law: str                    # the curve's law: "exp" or "polach"
    seed: int
    index: int
    curve: FrictionCurve | PolachCurve   # a PolachCurve's truth at the train speed at the fault
    mu_required: float
    t_det_target_s: float
    t_det_predicted_s: float
    peak_mu: float              # as drawn (the curve's peak() agrees to ~1e-9)
    peak_creep_kmh: float
    mu0: float                  # mu at zero creep
    shape: dict                 # the drawn shape numbers (module docstring)
    base: str                   # the base scenario's name

    @property
    def name(self) -> str:
        return f"{self.family}-{self.seed}-{self.index}"


def draw_rng(family: str, seed: int, index: int) -> np.random.Generator:
    """The draw's own stream: ``np.random.default_rng([seed, index, FAMILY_TAG[family]])``."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be >= 0, got seed {seed}, index {index}")
    return np.random.default_rng([int(seed), int(index), FAMILY_TAG[family]])


def draw(family: str, seed: int, index: int, base: Base | None = None) -> Draw:
    """Draw ``index`` of ``seed`` from ``family``: reproducible from (family, seed, index) and the base
    (default ``DEFAULT_BASE``, ffcc_a's).  Raises ValueError (one line) if the base admits no mu_required."""
    base = base or DEFAULT_BASE
    rng = draw_rng(family, seed, index)
    batch = sample_curves(family, 1, rng, base.initial_train_speed_ms)
    z = float(rng.random())                     # the T_det target's number, after the curve's
    curve = batch.curve(0)
    mp, vp = float(batch.peak_mu[0]), float(batch.peak_creep_kmh[0])
    where = f"family {family} draw {index} of seed {seed} (base {base.name})"
    lo, hi = _mu_required_range(base, mp, vp)
    if not hi > lo:
        raise ValueError(f"{where}: the base's NFCC-0 reaches only {hi:.4f} below the fault's peak creep "
                         f"{vp:.3f} km/h, not above its peak mu {mp:.4f}")
    fastest = float(predict_t_det(base, curve, hi, vp)[0])
    slowest = float(predict_t_det(base, curve, lo + (hi - lo) * 10 ** MIN_EXCESS_LOG10, vp)[0])
    t_lo = max(TDET_S[0], fastest * 1.001)
    t_hi = min(TDET_S[1], slowest * 0.999)
    if not t_lo < t_hi:
        raise ValueError(f"{where}: no mu_required gives T_det in [{TDET_S[0] * 1e3:.0f}, {TDET_S[1] * 1e3:.0f}] ms "
                         f"(fastest {fastest * 1e3:.1f} ms, slowest {slowest * 1e3:.1f} ms)")
    target = t_lo * (t_hi / t_lo) ** z
    mu_required = solve_mu_required(base, curve, mp, vp, target)
    v_f = float(train_speed_before_fault(base.vehicle, mu_required, base.initial_train_speed_ms, base.fault_time_s))
    if isinstance(curve, PolachCurve):
        curve = curve.at_train_speed(v_f)
    predicted = float(predict_t_det(base, curve, mu_required, vp)[0])
    shape = {k: float(v[0]) for k, v in batch.shape.items() if not math.isnan(v[0])}
    return Draw(family, "exp" if batch.law[0] == LAW_EXP else "polach", int(seed), int(index), curve,
                mu_required, target, predicted, mp, vp, float(batch.mu0[0]), shape, base.name)


# -- scenario text ---------------------------------------------------------------------------------------------------
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} {v!r} as TOML")


def _toml_table(lines: list[str], path: list[str], table: dict) -> None:
    scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in table.items() if isinstance(v, dict)}
    if path and (scalars or not tables):
        lines.append("")
        lines.append("[" + ".".join(_toml_key(p) for p in path) + "]")
    for k, v in scalars.items():
        if isinstance(v, list) and any(isinstance(x, dict) for x in v):
            raise TypeError(f"arrays of tables are not written ({'.'.join(path + [k])})")
        lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in tables.items():
        _toml_table(lines, path + [k], v)


def to_toml(data: dict, header: str = "") -> str:
    """A TOML document for ``data`` (what tomllib reads back: tables, scalars, arrays; no dates)."""
    lines = [f"# {line}" for line in header.splitlines()]
    _toml_table(lines, [], data)
    return "\n".join(lines).lstrip("\n") + "\n"


def curve_table(curve: FrictionCurve | PolachCurve) -> dict:
    """The ``[curves.fault]`` table of a curve (hil/config.py's keys).  A Polach curve's
    reference_train_speed_ms is left to the loader (the train speed at the fault, recomputed from [run])."""
    if isinstance(curve, PolachCurve):
        values = curve.values
        values.pop("reference_train_speed_ms")
        return {"model": "polach", **values}
    return {"model": "exp", "lambda0": float(curve.lambda0), "lambdas": [float(x) for x in curve.lambdas],
            "taus": [float(x) for x in curve.taus]}


def draw_scenario_text(base_text: str, family: str, seed: int, index: int) -> str:
    """``base_text`` (a scenario's TOML) with ``[curves.fault]`` and ``[run] mu_required`` replaced by the draw's,
    ``name`` = ``<family>-<seed>-<index>`` and a ``description`` naming the draw; every other table kept
    (comments are not).  mu_required is chosen for this base (its vehicle, NFCC-0, train speed, fault time)."""
    data = tomllib.loads(base_text)
    base = Base.from_text(base_text)
    d = draw(family, seed, index, base)
    data = {"name": d.name, "description": "", **{k: v for k, v in data.items() if k not in ("name", "description")}}
    data["description"] = (f"family {family} draw {index} of seed {seed}: {d.law} curve, peak mu {d.peak_mu:.4f} at "
                           f"{d.peak_creep_kmh:.3f} km/h, mu_required {d.mu_required:.4f}, T_det target "
                           f"{d.t_det_target_s * 1e3:.1f} ms (base {base.name})")
    data.setdefault("curves", {})["fault"] = curve_table(d.curve)
    data["run"]["mu_required"] = d.mu_required
    header = (f"drawn by plant/families.py: family {family}, seed {seed}, index {index} ({d.law} law), base "
              f"{base.name}\nT_det target {d.t_det_target_s * 1e3:.2f} ms, predicted "
              f"{d.t_det_predicted_s * 1e3:.2f} ms; shape {json.dumps(d.shape)}")
    return to_toml(data, header)


# -- the spec ----------------------------------------------------------------------------------------------------
def describe(family: str) -> dict:
    """The family's documented spec (module docstring) as JSON-serialisable data."""
    if family not in FAMILIES:
        raise ValueError(f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
    laws = {"exp": ["exp"], "polach": ["polach"], "default": ["exp", "polach"]}[family]
    shapes = {
        "exp": {"mu0": {"distribution": "uniform", "range": list(EXP_MU0)},
                "asymptote_ratio": {"distribution": "uniform", "range": list(EXP_ASYMPTOTE_RATIO),
                                    "meaning": "lambda0 / peak mu: 0 falls to zero (steep), 0.7 keeps 70 % (gentle)"},
                "term_ratio": {"distribution": "log-uniform", "range": list(EXP_TERM_RATIO), "meaning": "tau2 / tau1"},
                "solved": "lambda0, lambda1, lambda2, tau1, tau2 from peak mu, peak creep, mu0, asymptote and term "
                          "ratios; monotone rise to the one peak, monotone fall after it"},
        "polach": {"mu0": {"value": 0.0},
                   "A": {"distribution": "uniform", "range": list(POLACH_A)},
                   "b_at_peak": {"distribution": "log-uniform", "range": list(POLACH_B_AT_PEAK),
                                 "meaning": "B_s_per_m * peak slip velocity (m/s): small gentle, large steep"},
                   "k_A": {"distribution": "uniform", "range": list(POLACH_K_A)},
                   "ks_ratio": {"distribution": "uniform", "range": list(POLACH_KS_RATIO), "meaning": "k_S / k_A"},
                   "solved": "stiffness (peak at the drawn creep) and mu_static (the drawn peak mu) at the train "
                             "speed at the fault"},
    }
    return {
        "family": family,
        "summary": FAMILIES[family],
        "laws": laws,
        "law_choice": "fair coin per curve, the first number of its stream" if family == "default" else "fixed",
        "peak_mu": {"distribution": "uniform", "range": list(PEAK_MU)},
        "peak_creep_kmh": {"distribution": "log-uniform", "range": list(PEAK_CREEP_KMH)},
        "joint_rule": {"rule": "peak_mu <= headroom * N(min(peak_creep_kmh, N's peak creep)), by rejection",
                       "headroom": HEADROOM, "N": [float(x) for x in REFERENCE_NORMAL.params],
                       "N_peak_creep_kmh": _REF_PEAK_KMH},
        "shape": {law: shapes[law] for law in laws},
        "curve_at": "the train speed at the fault (plant.model.train_speed_before_fault)",
        "t_det_target_s": {"distribution": "log-uniform", "range": list(TDET_S),
                           "lower_end": "raised to the fastest T_det any admissible mu_required gives, "
                                        "when above 20 ms"},
        "mu_required": "solves predicted T_det = target on (peak mu, NFCC-0 at min(peak creep, NFCC-0's peak creep))",
        "rng": "np.random.default_rng([seed, index, tag]), tag " + str(FAMILY_TAG[family]),
    }


__all__ = ["Base", "CurveBatch", "DEFAULT_BASE", "Draw", "FAMILIES", "FAMILY_TAG", "describe", "draw", "draw_rng",
           "draw_scenario_text", "exp_coefficients", "polach_parameters", "predict_t_det", "sample_curves",
           "to_toml"]
