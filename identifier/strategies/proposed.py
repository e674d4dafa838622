"""The paper's proposed strategy: NLLS preliminary fit + MDIPF + dynamic projection domain +
multi-level evaluation (§3.2-3.5), and a variant that adds physics the paper ignores.

Dynamic projection domain (§3.4, eq. 22-24): correction Q keeps every error particle chi inside a
box Omega_Q = [lo, hi].  After each correction the box contracts, literally

    lo_{Q+1} = lo_Q + delta_dn * |chi^_Q - chi^_{Q-1}|,   hi_{Q+1} = hi_Q - delta_up * |chi^_Q - chi^_{Q-1}|

never below ``min_width_fraction`` of its first width (the paper does not say what happens when
the two sides cross; we stop them at that width, about the box's middle).  Particles outside are
projected in by ``pf.project_to_box`` (``projector``: "map" solves eq. 24 by projected Gauss-Newton,
"clip" is the Euclidean projection).  ``box_recentre``: the box lives in chi-space, i.e. it moves
with theta and stays centred on the latest estimate (True, default), or stays fixed in parameter
space around the preliminary fit (False).

``ProposedFastStrategy`` (beyond the paper): see its docstring.

``ProposedMu0Strategy`` (beyond the paper): the fault curves satisfy mu(0) = 0, i.e.
lambda0 + sum(lambda_i) = 0 (a wheel that does not slip transmits no creep force).  The
preliminary NLLS fits n*2 free parameters with lambda0 = -sum(lambda_i), and every particle is
kept on that plane (xi0 = -sum(xi_i) - (lambda0 + sum lambda_i of theta)), so the filter searches
one dimension less and the early, low-creep samples cannot tilt the curve's offset.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

from .. import pf
from ..curve import jacobian, mu_model
from .mdipf import DEFAULTS as MDIPF_DEFAULTS
from .mdipf import MdipfStrategy, per_dimension
from .nlls import parameter_bounds

# Defaults (chosen with hil bench identify; figures in docs/design/identifier.md): with the stabilised
# Theta the box half-widths and "clip" vs "map" projection change RT and peak errors by less than the
# seed-to-seed spread (the box binds few particles before the 2nd correction, after
# which the confidence check usually confirms); Delta_dn = Delta_up = 0.5 and box_recentre only act
# from the 2nd correction on, i.e. when a confidence check failed.  The defaults are the physical
# scales: +-3 initial sigmas.
# Projection: "clip" (the Euclidean projection) by default; "map" (eq. 24 literally: projected
# Gauss-Newton on prior + measurement) is kept as ``projector = "map"``.  The two give the same RT
# and peak errors within the seeds' spread; about half the cloud leaves the box each step, and "map"
# costs far more per step for them than "clip".
PROPOSED_DEFAULTS = {
    **MDIPF_DEFAULTS,
    "box_halfwidth": [0.01, 0.06, 0.09],     # initial Omega: +- this around chi = 0 (lambda0, lambda_i, tau_i)
    "delta_dn": 0.5,                          # Delta_dn
    "delta_up": 0.5,                          # Delta_up
    "min_width_fraction": 0.1,
    "box_recentre": True,
    "projector": "clip",                      # "map": eq. 24 literally (see the note above PROPOSED_DEFAULTS)
    "projection_iterations": 1,               # Gauss-Newton steps of the "map" projection (2 and 3: same results)
}


class ProposedStrategy(MdipfStrategy):
    name = "proposed"
    defaults = PROPOSED_DEFAULTS

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        n = (self.theta.size - 1) // 2
        half = per_dimension(self.opts["box_halfwidth"], n)
        if np.any(half <= 0):
            raise ValueError(f"{self.name}: box_halfwidth must be > 0")
        self.lo, self.hi = -half, half.copy()
        self.min_width = 2 * half * float(self.opts["min_width_fraction"])
        self._prev_estimate = np.zeros(self.theta.size)
        self.boxes: list[tuple[np.ndarray, np.ndarray]] = []    # (lo, hi) per correction, for plots
        self._box_changed = False
        # the first cloud is drawn before the fault (mdipf.py): put it into the first box now too
        self._clip_into_box(self._next_cloud)
        self._first_cloud_in_box = True

    def _clip_into_box(self, xt) -> None:
        np.maximum(xt, self.lo[:, None], out=xt)
        np.minimum(xt, self.hi[:, None], out=xt)

    def _after_prelim(self) -> None:
        if not self._first_cloud_in_box:                          # a cloud drawn now: into the first box
            self._clip_into_box(self._xt)
            self._constrain()                                     # (_draw_cloud constrained it before the clip)
        self._first_cloud_in_box = False

    def _after_recentre(self) -> None:
        # no measurement at hand between windows: the Euclidean projection into the new box (in place)
        self._clip_into_box(self._xt)
        self._constrain_in_box()

    def _recentre_changes(self, chi) -> bool:
        return self._box_changed or bool(chi.any())

    def _can_fuse_projection(self) -> bool:
        return self.opts["projector"] == "clip" and self.plain_projection and self.plain_constrain

    def _clip_box(self):
        return self.lo, self.hi, True

    def _project(self, creep_speed_kmh, mu_hat) -> None:
        # the cloud is finite here (_constrain ran): "clip" is np.clip in place (pf.project_to_box's
        # "clip" to the last bit); "map" first checks cheaply whether any particle is outside
        xt = self._xt
        lo, hi = self.lo[:, None], self.hi[:, None]
        if self.opts["projector"] == "clip":
            np.maximum(xt, lo, out=xt)
            np.minimum(xt, hi, out=xt)
        else:
            inside = np.maximum(xt, lo, out=self._d)
            np.minimum(inside, hi, out=inside)
            if not np.array_equal(inside, xt):
                self.particles = pf.project_to_box(self._xt.T, self.lo, self.hi, self.base, creep_speed_kmh, mu_hat,
                                                   self.init_std, self.noise_std, self.opts["projector"],
                                                   int(self.opts["projection_iterations"]))
        self._constrain_in_box()

    def _constrain_in_box(self) -> None:
        """Hook for constrained variants: re-impose the constraint without leaving the box."""

    def _after_correction(self, estimate) -> None:
        # the box contraction on 2n + 1 numbers, with Python floats (numpy calls on 5-element
        # arrays cost more than their arithmetic on the sample that closes a window)
        est = np.asarray(estimate, float).tolist()
        prev = self._prev_estimate.tolist()
        recentre = bool(self.opts["box_recentre"])
        if est == prev and (recentre or not any(est)):   # nothing moves (the prelim's chi^_0 = 0): the same box
            self._box_changed = False
            self.boxes.append((self.lo.copy(), self.hi.copy()))
            return
        dn, up = float(self.opts["delta_dn"]), float(self.opts["delta_up"])
        lo, hi = [], []
        for e, e_prev, l0, h0, w in zip(est, prev, self.lo.tolist(), self.hi.tolist(), self.min_width.tolist()):
            change = abs(e - e_prev)
            lo_i, hi_i = l0 + dn * change, h0 - up * change
            if hi_i - lo_i < w:                           # never narrower than min_width: stop at the middle
                mid = 0.5 * (lo_i + hi_i)
                lo_i, hi_i = mid - 0.5 * w, mid + 0.5 * w
            if not recentre:                              # fixed in parameter space: shift with the new origin
                lo_i, hi_i = lo_i - e, hi_i - e
            lo.append(lo_i)
            hi.append(hi_i)
        self._prev_estimate = np.array(est)
        self._box_changed = not any(math.isnan(x) for x in lo + hi)
        if self._box_changed:
            self.lo, self.hi = np.array(lo), np.array(hi)
        self.boxes.append((self.lo.copy(), self.hi.copy()))


def fit_curve_mu0(creep_speed_kmh, mu_samples, theta0, radius=None) -> np.ndarray:
    """NLLS with lambda0 = -sum(lambda_i) (mu(0) = 0): fits lambda_1..n, tau_1..n."""
    v = np.asarray(creep_speed_kmh, float)
    y = np.asarray(mu_samples, float)
    theta0 = np.asarray(theta0, float)
    n = (theta0.size - 1) // 2
    lo, hi = parameter_bounds(n, theta0, radius)
    lo, hi = lo[1:], hi[1:]

    def full(x):
        return np.r_[-np.sum(x[:n]), x]

    def jac(x):
        j = jacobian(v, full(x))
        return j[:, 1:] + np.hstack([-j[:, :1] * np.ones((1, n)), np.zeros((v.size, n))])

    start = np.clip(theta0[1:], lo + 1e-9, hi - 1e-9)
    res = least_squares(lambda x: mu_model(v, full(x)) - y, start, jac=jac, method="trf", bounds=(lo, hi),
                        x_scale="jac", max_nfev=200)
    return full(res.x)


class ProposedMu0Strategy(ProposedStrategy):
    name = "proposed_mu0"
    plain_step = plain_constrain = plain_prelim = False     # mu(0) = 0: its own constraint and prelim

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        self.lo[0], self.hi[0] = -np.inf, np.inf     # xi0 follows from the others: no box of its own

    def preliminary_fit(self, window_v, window_mu):
        return fit_curve_mu0(window_v, window_mu, self.theta, self.prelim_radius())

    def _constrain(self) -> None:
        super()._constrain()
        n = (self.base.size - 1) // 2
        offset = self.base[0] + np.sum(self.base[1:1 + n])
        self.particles[:, 0] = -np.sum(self.particles[:, 1:1 + n], axis=1) - offset

    def _constrain_in_box(self) -> None:
        # xi0 is determined by the others; keep it in the box by clipping, the plane wins ties
        self._constrain()
