"""Friction (adhesion) characteristic curves of the paper's form (eq. 3).

    mu(v_s) = lambda0 + sum_i lambda_i * exp(tau_i * v_s)

with the creep speed ``v_s`` in **km/h**.  Any number of exponential terms is allowed; the
paper's curves use two.  The same class evaluates on numpy arrays (identifier, metrics) and on
CasADi symbols (plant), so the plant and the truth used by the metrics cannot drift apart.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import brentq, minimize_scalar

#: creep-speed range (km/h) searched for a curve's peak; every curve of interest peaks well inside.
PEAK_SEARCH_KMH = (0.0, 30.0)


@dataclass(frozen=True)
class FrictionCurve:
    """mu(v_s) = lambda0 + sum(lambdas[i] * exp(taus[i] * v_s)), v_s in km/h."""

    lambda0: float
    lambdas: tuple[float, ...]
    taus: tuple[float, ...]
    name: str = ""

    def __post_init__(self):
        if len(self.lambdas) != len(self.taus):
            raise ValueError(f"curve {self.name!r}: {len(self.lambdas)} lambdas but {len(self.taus)} taus")
        if not self.lambdas:
            raise ValueError(f"curve {self.name!r}: needs at least one exponential term")

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_params(cls, params: Sequence[float], name: str = "") -> "FrictionCurve":
        """From the flat vector (lambda0, lambda1..n, tau1..n) used by the identifiers."""
        p = [float(x) for x in params]
        if len(p) < 3 or len(p) % 2 == 0:
            raise ValueError(f"curve {name!r}: parameter vector must have length 1 + 2n, got {len(p)}")
        n = (len(p) - 1) // 2
        return cls(p[0], tuple(p[1:1 + n]), tuple(p[1 + n:]), name)

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

    def mu_casadi(self, creep_speed_kmh):
        """Same curve on a CasADi expression; odd-symmetric so that braking creep brakes."""
        import casadi as ca

        v = ca.fabs(creep_speed_kmh)
        mu = self.lambda0
        for lam, tau in zip(self.lambdas, self.taus):
            mu = mu + lam * ca.exp(tau * v)
        return ca.sign(creep_speed_kmh) * mu

    # -- shape ----------------------------------------------------------------------------
    def peak(self) -> tuple[float, float]:
        """(creep speed in km/h, mu) at the curve's maximum in PEAK_SEARCH_KMH."""
        grid = np.linspace(*PEAK_SEARCH_KMH, 3001)
        i = int(np.argmax(self.mu(grid)))
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        if hi <= lo:
            return float(grid[i]), float(self.mu(grid[i]))
        res = minimize_scalar(lambda v: -float(self.mu(v)), bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-9})
        return float(res.x), float(-res.fun)

    def creep_for_mu(self, mu_target: float) -> float:
        """Creep speed (km/h) on the stable (rising) side where the curve reaches ``mu_target``."""
        v_peak, mu_peak = self.peak()
        mu0 = float(self.mu(0.0))
        if not (mu0 <= mu_target <= mu_peak):
            raise ValueError(f"curve {self.name!r}: mu {mu_target} is outside its stable range "
                             f"[{mu0:.4f}, {mu_peak:.4f}]")
        if mu_target == mu_peak:
            return v_peak
        return float(brentq(lambda v: float(self.mu(v)) - mu_target, 0.0, v_peak, xtol=1e-12))
