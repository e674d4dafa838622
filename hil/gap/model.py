"""The nominal model (and the nominal model plus one candidate effect) replayed on a real log's inputs.

* ``Simulator``: the CasADi period step of ``plant.reality.RealityModel`` rolled over the whole run
  with ``mapaccum`` (one call simulates every period, so a least-squares fit can afford hundreds of
  whole-run simulations), the fitted effect parameters as a vector input; a fit that reads only the
  first periods (the training blocks of the analysis window) simulates only those.  The step is
  compiled to C where a compiler is (``hil.gap.compiled``: the same bits, faster).
* ``observer_mu_hat``: the TCU's load-torque observer (identifier/observer.py, eq. 4-5) as a linear
  filter over whole arrays (scipy ``lfilter``), so the model's mu^ is computed exactly the way the
  TCU computes it, without a Python loop per sample.
* ``shift``: a fractional delay of a sampled signal (linear interpolation, held at the start).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
from scipy import signal

from plant.params import KMH_PER_MS
from .compiled import compiled
from identifier.observer import LoadTorqueObserver
from plant.reality import RealityModel


def initial_line(t_s, motor, train, n_fit: int = 20, n_fit_train: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """(value at t_s[0], slope per second) of (omega_m, v_t) from straight-line fits to the first
    ``n_fit`` motor-speed samples (it may have a fast transient) and ``n_fit_train`` train-speed samples
    (the train's inertia keeps it straight; its error moves the creep, so the motor too)."""
    values, slopes = [], []
    for y, n in ((motor, n_fit), (train, n_fit_train)):
        n = min(n, len(y))
        a, b = np.polyfit(t_s[:n] - t_s[0], y[:n], 1)
        values.append(b)
        slopes.append(a)
    return np.array(values), np.array(slopes)


class Simulator:
    """``run(theta, x0, torque) -> (motor_rad_s, train_ms)`` at every step k (state at t_k)."""

    def __init__(self, cfg, effect: str | None, fit_params: tuple[str, ...], fixed: dict, n: int,
                 base: dict | None = None):
        """``effect``: a plant-level effect name or None (nominal); ``fit_params``: its parameters that
        ``theta`` gives; ``fixed``: its other parameters; ``base``: plant effects {name: params} held
        fixed underneath (forward selection builds on the effect found first)."""
        self.cfg = cfg
        self.n = n
        self.base = {k: dict(v) for k, v in (base or {}).items()}
        self.theta = ca.SX.sym("theta", max(len(fit_params), 1))
        effects = {k: dict(v) for k, v in self.base.items()}
        if effect is not None:
            params = dict(fixed)
            for i, name in enumerate(fit_params):
                params[name] = self.theta[i]
            effects[effect] = params
        self.model = RealityModel(cfg, effects)
        self._fixed_effects = effects
        step = self.model.period_step(self.theta)
        # the same expressions with their repeats computed once (CasADi's common-subexpression
        # elimination merges nodes of one operation on the same operands: the same values, fewer
        # instructions for the SX virtual machine to run every period)
        xs = step.sx_in()
        self.step_vm = ca.Function("gap_step", xs, step.call(xs, True, False), {"cse": True})
        self._step = compiled(self.step_vm)     # C where a compiler is: the same bits, faster
        self._sims = {n: self._step.mapaccum("gap_sim", n - 1)}     # periods simulated -> the rolled step
        self.fit_params = fit_params
        self.effect = effect

    def initial(self, theta, x0, torque0):
        """Full initial state (extra states consistent with the nominal ones) for parameters theta."""
        if self.effect is None and not self.base:
            return np.asarray(x0, float)
        effects = dict(self.base)
        if self.effect is not None:
            effects[self.effect] = {k: (float(theta[self.fit_params.index(k)]) if k in self.fit_params else v)
                                    for k, v in self._fixed_effects[self.effect].items()}
        return RealityModel(self.cfg, effects).initial_state(x0, torque0)

    def run(self, theta, x0, torque, t0: float = 0.0, n: int | None = None):
        """The states at the first ``n`` steps (default: every step of the run).  A fit that reads only
        the first n periods simulates only those: the same step rolled fewer times, so the same values."""
        n = self.n if n is None else min(int(n), self.n)
        if n not in self._sims:
            self._sims[n] = self._step.mapaccum("gap_sim", n - 1)
        theta = np.atleast_1d(np.asarray(theta, float)) if len(self.fit_params) else np.zeros(1)
        xi = self.initial(theta, x0, float(torque[0]))
        period = self.cfg.exchange_period_s
        times = t0 + np.arange(n - 1) * period
        x = np.asarray(self._sims[n](xi, torque[None, :n - 1], times[None, :], theta)[0])
        motor = np.concatenate([[xi[0]], x[0]])
        train = np.concatenate([[xi[1]], x[1]])
        if not (np.all(np.isfinite(motor)) and np.all(np.isfinite(train))):
            raise FloatingPointError("model diverged")
        return motor, train

    def ahead(self, motor, train, torque, periods: int, t0: float = 0.0) -> np.ndarray:
        """omega_m predicted ``periods`` ahead from every measured state: ``out[k]`` is the model's motor
        speed at step k + periods when started from (motor[k], train[k]) at t_k under the logged
        commands (NaN for the last ``periods`` steps).  What the measured speed then differs by is
        the model's equation error at the measured state (``hil.gap.sparse``); the nominal model's
        state is (omega_m, v_t) and nothing else, so only it (no effect, no base) can start there."""
        if self.effect is not None or self.base:
            raise ValueError("ahead(): only the nominal model starts from a measured state")
        n = len(motor)
        step = self._step.map(n)
        x = np.vstack([np.asarray(motor, float), np.asarray(train, float)])
        times = t0 + self.cfg.exchange_period_s * np.arange(n)
        for j in range(periods):
            k = np.minimum(np.arange(n) + j, n - 1)
            x = np.asarray(step(x, torque[k][None, :], times[k][None, :], np.zeros((1, n)))[0])
        out = np.full(n, np.nan)
        out[:n - periods] = x[0, :n - periods]
        return out


class ObserverReplica:
    """mu^(k) exactly as TractionIdentifier computes it from measured speeds and commands."""

    def __init__(self, settings):
        v = settings.vehicle
        # the TCU's own observer, as one linear system (inputs T_e', y'; output T^_L)
        A, B, C = LoadTorqueObserver(v.equivalent_inertia_kgm2, settings.period_s,
                                     settings.observer_pole_rad_s).state_space()
        self.tf = [signal.ss2tf(A, B, C, np.zeros((1, 2)), input=i) for i in (0, 1)]
        self.torque_per_mu = v.torque_per_mu_nm
        self.torque_demand = settings.torque_demand_nm
        self.vehicle = v

    def mu_hat(self, motor, torque_cmd) -> np.ndarray:
        """``motor``: the speeds the TCU received; ``torque_cmd[k]`` answers reading k, so the observer
        at k uses ``torque_cmd[k-1]`` (the demand at k = 0)."""
        te = np.concatenate([[self.torque_demand], torque_cmd[:-1]])
        y0, te0 = motor[0], te[0]
        out = np.full(len(motor), te0)
        for (num, den), u in zip(self.tf, (te - te0, motor - y0)):
            out = out + signal.lfilter(num[0], den, u)
        return out / self.torque_per_mu

    def creep_kmh(self, motor, train):
        v = self.vehicle
        return KMH_PER_MS * (motor / v.gear_ratio * v.wheel_radius_m - train)

    def noise_gain(self, n: int = 20000) -> float:
        """std of mu^ per unit std of white noise on the motor speed (a fixed, seeded draw)."""
        e = np.random.default_rng(12345).standard_normal(n)
        mu = self.mu_hat(e, np.full(n, self.torque_demand))
        return float(np.std(mu[200:]))


def shift(x: np.ndarray, delay_periods: float) -> np.ndarray:
    """x delayed by a (fractional) number of periods; values before the start hold x[0]."""
    if delay_periods <= 0:
        return x
    k = np.arange(len(x), dtype=float) - delay_periods
    return np.interp(k, np.arange(len(x), dtype=float), x)


def lowpass(x: np.ndarray, tau_periods: float) -> np.ndarray:
    """x through the first-order low-pass ``y_k = a y_(k-1) + (1 - a) x_k``, ``a = exp(-1/tau)``, from
    ``y_0 = x_0`` (as ``plant.reality.RealitySensors`` filters a reading per period)."""
    if tau_periods <= 0:
        return x
    from scipy.signal import lfilter
    a = math.exp(-1.0 / tau_periods)
    y, _ = lfilter([1 - a], [1.0, -a], x[1:], zi=[a * x[0]])
    return np.concatenate([x[:1], y])


def lattice_quantum(values: np.ndarray, q_min: float, q_max: float) -> tuple[float, float]:
    """(quantum, coherence): the spacing q of the lattice the values sit on, and how well they do.

    Quantised readings move in whole steps, so the smallest non-zero steps between consecutive values
    give q; it is then refined on the values themselves (k = round(y/q), q = sum(y k) / sum(k^2)).
    Coherence |mean exp(2 pi i x / q)| is 1 for values exactly on the lattice and near 0 for continuous
    ones; the smaller of the steps' and the values' coherence is returned.  Noise added after the
    quantiser (issue 51) makes a reading that stays on one lattice point step by far less than q, so
    the smallest steps miss the lattice: then the steps' upper quantiles (``UPPER_STEP_QUANTILES``:
    the steps from one lattice point to the next) start the same refinement, the steps near zero left
    out (k = 0), and the lattice is judged by the values' coherence alone (lowered by the noise only by
    exp(-2 pi^2 s^2 / q^2), 0.98 at s = q / 30, however often the values repeat); the most coherent
    answer is returned, or the largest multiple of it about as coherent (a lattice's submultiples are
    lattices too).  (0, 0) when nothing fits in [q_min, q_max].
    """
    y = np.asarray(values, float)
    y = y[np.isfinite(y)]
    d = np.abs(np.diff(y))
    d = d[d > 1e-12 * max(1.0, float(np.max(np.abs(y))) if y.size else 1.0)]
    if d.size < 10:
        return 0.0, 0.0
    best = (0.0, 0.0)
    q = float(np.quantile(d, 0.02))
    if q_min <= q <= q_max:
        k = np.maximum(np.round(d / q), 1)
        q = float(np.sum(d * k) / np.sum(k * k))
        coh_d = float(np.abs(np.exp(2j * math.pi * d / q).mean()))
        q = _refined_on_values(y, q)
        best = (q, min(coh_d, _coherence(y, q)))
    if best[1] > 0.9:
        return best
    tried: list[float] = []
    for quantile in UPPER_STEP_QUANTILES:          # noise after the quantiser
        q = float(np.quantile(d, quantile))
        if not q_min <= q <= q_max:
            continue
        for _ in range(3):                           # the steps between neighbouring lattice points
            k = np.round(d / q)
            if not np.any(k):
                break
            q = float(np.sum(d * k) / np.sum(k * k))
        if not (q_min <= q <= q_max and np.any(k)):
            continue
        q = _refined_on_values(y, q)
        coh = _coherence(y, q)
        if coh <= 0.9 and any(abs(q / p - 1) < 0.03 for p in tried):
            continue                                 # polished already
        tried.append(q)
        if coh <= 0.9:
            q = _polished(y, q)
            coh = _coherence(y, q)
        if q_min <= q <= q_max and coh > best[1]:
            best = (q, coh)
        if best[1] > 0.97:
            break
    if 0 < best[1] <= 0.9 or best[0] == 0:
        return best
    # values on a lattice are on every submultiple of it too (less coherent under the noise only by a
    # little when the noise is small): the lattice is the largest multiple as coherent as what was found
    q, coh = best
    for m in (5, 4, 3, 2):
        qm = _refined_on_values(y, m * q)
        cm = _coherence(y, qm)
        if q_min <= qm <= q_max and cm >= coh - 0.05:
            return qm, cm
    return best


def _polished(y: np.ndarray, q: float, points: int = 241, width: float = 0.03) -> float:
    """The most coherent q within +-``width`` of ``q`` (a grid): the steps' refinement under noise may
    land a fraction of a per cent off, and the values' phase drifts by that times y / q cycles."""
    grid = q * np.linspace(1 - width, 1 + width, points)
    ref = float(np.median(y))
    d = y - ref
    coh = np.abs(np.exp(2j * math.pi * (d[None, :] / grid[:, None] + ref / grid[:, None])).mean(axis=1))
    return _refined_on_values(y, float(grid[int(np.argmax(coh))]))


#: the quantiles of the steps between consecutive values that start ``lattice_quantum``'s search under
#: noise after the quantiser (a reading moves to the next lattice point in a few per cent of the
#: periods to most of them, as the speed moves slowly or fast)
UPPER_STEP_QUANTILES = (0.5, 0.8, 0.9, 0.95, 0.98, 0.99)


def _refined_on_values(y: np.ndarray, q: float) -> float:
    for _ in range(3):
        k = np.round(y / q)
        q = float(np.sum(y * k) / np.sum(k * k))
    return q


def _coherence(y: np.ndarray, q: float) -> float:
    return float(np.abs(np.exp(2j * math.pi * y / q).mean()))
