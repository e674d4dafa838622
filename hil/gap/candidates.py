"""Candidate explanations of a sim-to-real gap, each with its own parameter fit.

A candidate predicts the three measured signals -- motor speed and train speed (plant-side sensor
frames) and the TCU's mu^ -- plus the noise floor it expects on each.  Plant-level candidates are fitted
by ``scipy.optimize.least_squares`` on the training blocks (after a coarse scan of their parameter
range, so a local method starts in the right basin); delay candidates by a scan plus a bounded
scalar search; quantisation by the lattice its values sit on (a quantiser changes the noise, not
the mean, so least squares cannot see it).

Only the parameters marked here are fitted; the rest keep the scenario's/default values:
``load_transfer`` fits z (bogie height; L, L_b, Z from the scenario), ``compliance`` fits stiffness
and damping ratio (backlash is invisible while the torque keeps one sign), ``can`` fits the mean
delay (jitter and loss act as noise).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from plant.reality import fill_defaults

from ..effects import EFFECTS, DelayFit, PlantFit

from .model import Simulator, lattice_quantum, lowpass, shift

SIGNALS = ("motor", "train", "mu_hat")
#: the sensor-side forms a context can hold underneath its models (periods): ``Context.predict``'s
#: arguments, and the ``Fit.extra`` keys a sensor-form candidate leaves for forward selection
SENSOR_FORMS_OF_CONTEXT = ("sensor_delay", "can_delay", "lowpass_tau", "motor_delay")
UNITS = {"motor": "rad/s", "train": "m/s", "mu_hat": "-", "creep": "km/h"}


@dataclass
class Fit:
    name: str
    params: dict                      # fitted parameters, in the effect's units
    k: int                            # number of fitted parameters
    pred: dict                        # signal -> model prediction (whole run)
    sigma: dict                       # signal -> noise floor the candidate expects
    train_cost: float = math.nan
    note: str = ""
    extra: dict = field(default_factory=dict)   # sensor/can delays for replays (periods)


def periods_read(mask, n: int) -> int:
    """The number of leading periods ``mask`` reads (up to its last True, at least two; ``n`` when it
    reads none)."""
    hit = np.flatnonzero(mask)
    return max(int(hit[-1]) + 1, 2) if hit.size else n


class Context:
    """Everything a fit needs: the data, the scenario's model, noise floors, the block split."""

    def __init__(self, data, scenario, observer, x0, window, train_mask, held_mask, sigma_nom, x0_slope=None):
        self.data = data
        self.x0_slope = np.zeros(2) if x0_slope is None else np.asarray(x0_slope, float)
        self.scenario = scenario
        self.cfg = scenario.plant_config()
        self.observer = observer
        self.x0 = x0
        self.window = window
        #: the periods a fit reads (its residuals are on the training blocks, in the analysis window):
        #: the simulations inside a fit stop at the last of them (the fitted model covers the whole run)
        self.n_read = periods_read(train_mask, data.n)
        self.train = train_mask
        self.held = held_mask
        self.sigma_nom = sigma_nom
        self.meas = {"motor": data.motor_speed_rad_s, "train": data.train_speed_ms, "mu_hat": data.tcu_mu_hat}
        self.valid = {s: np.isfinite(v) for s, v in self.meas.items()}
        self._sims = {}
        self.base_effects = {}                                  # plant effects held fixed underneath
        self.base_delays = {k: 0.0 for k in SENSOR_FORMS_OF_CONTEXT}   # and sensor forms (periods)
        self.base_names = ()

    def simulator(self, effect, fit_params, fixed):
        key = (effect, fit_params, repr(sorted(fixed.items())), repr(sorted(self.base_effects.items())))
        if key not in self._sims:
            self._sims[key] = Simulator(self.cfg, effect, fit_params, fixed, self.data.n, self.base_effects)
        return self._sims[key]

    def on_top_of(self, fit: "Fit") -> "Context":
        """This context with ``fit``'s effect held fixed underneath every model (forward selection)."""
        import copy
        c = copy.copy(self)
        c.base_effects = dict(self.base_effects)
        c.base_delays = dict(self.base_delays)
        if "plant" in fit.extra:
            name, params = fit.extra["plant"]
            c.base_effects[name] = dict(params)
        for k in SENSOR_FORMS_OF_CONTEXT:
            c.base_delays[k] += fit.extra.get(k, 0.0)
        if "can_frames" in fit.extra:
            c.base_delays["can_delay"] += fit.params["delay_ms"] * 1e-3 / self.data.period_s
        c.base_names = self.base_names + (fit.name,)
        return c

    def split(self, train_mask, held_mask) -> "Context":
        """This context fitted on ``train_mask`` and judged on ``held_mask`` (forward selection's veto from
        data held out in time); the simulators are shared (they do not depend on the split)."""
        import copy
        c = copy.copy(self)
        c.train, c.held = train_mask, held_mask
        c.n_read = periods_read(train_mask, self.data.n)
        return c

    def on_top_of_effects(self, effects: dict, **sensor_periods) -> "Context":
        """This context with plant ``effects`` {name: full params} and sensor forms (periods, by
        ``SENSOR_FORMS_OF_CONTEXT`` key) held fixed underneath every model (the bench's oracle: the
        truth as the model)."""
        import copy
        c = copy.copy(self)
        c.base_effects = {**self.base_effects, **{k: dict(v) for k, v in effects.items()}}
        c.base_delays = dict(self.base_delays)
        for k, v in sensor_periods.items():
            c.base_delays[k] += v
        c.base_names = self.base_names + tuple(effects)
        return c

    def predict(self, motor, train, sensor_delay=0.0, can_delay=0.0, lowpass_tau=0.0, motor_delay=0.0) -> dict:
        """Measured-signal predictions from the plant trajectory: sensors low-pass it with
        ``lowpass_tau`` periods, see it ``sensor_delay`` periods late and the motor encoder another
        ``motor_delay``; the TCU sees the sensor values another ``can_delay`` periods late (each plus
        the base's), in ``plant.reality.RealitySensors``' order."""
        b = self.base_delays
        motor, train = lowpass(motor, lowpass_tau + b["lowpass_tau"]), lowpass(train, lowpass_tau + b["lowpass_tau"])
        sensor_delay += b["sensor_delay"]
        m_s, t_s = shift(motor, sensor_delay), shift(train, sensor_delay)
        m_s = shift(m_s, motor_delay + b["motor_delay"])
        m_tcu = shift(m_s, can_delay + b["can_delay"])
        torque = self.data.torque_cmd_nm[:len(motor)]        # a trajectory of the first periods only
        return {"motor": m_s, "train": t_s, "mu_hat": self.observer.mu_hat(m_tcu, torque)}

    def residuals(self, pred: dict, sigma: dict, mask) -> np.ndarray:
        """(measured - predicted) / sigma on ``mask``, signal after signal; ``pred`` may cover only the
        first periods (a fit's simulation up to ``n_read``), never fewer than ``mask`` reads."""
        n = len(pred[SIGNALS[0]])
        if np.any(mask[n:]):
            raise ValueError(f"a prediction of {n} periods cannot be judged on a mask reading period "
                             f"{int(np.flatnonzero(mask)[-1])}")
        out = []
        for s in SIGNALS:
            sel = (mask & self.valid[s])[:n]
            out.append((self.meas[s][:n][sel] - pred[s][sel]) / sigma[s])
        return np.concatenate(out)


# -- candidates --------------------------------------------------------------------------------------
#: the measured initial state is a nuisance pair fitted with every model (nominal included), within
#: X0_BOUND sensor-noise standard deviations of the straight-line estimate over the first 20 ms (whose
#: own error is a fraction of one: docs/design/gap-diagnosis.md)
X0_BOUND = 5.0


def _fit_ls(resid, u0, lo, hi, scale, starts=None, sigma=None):
    """least_squares over u = (parameters, dx0) from each start; the best result."""
    s = np.array([sigma["motor"], sigma["train"]])
    lo = np.concatenate([lo, -X0_BOUND * s])
    hi = np.concatenate([hi, X0_BOUND * s])
    scale = np.concatenate([scale, s])
    best = None
    for u in (starts if starts is not None else [u0]):
        u = np.clip(np.concatenate([u, np.zeros(2)]) if len(u) == len(lo) - 2 else u, lo, hi)
        r = least_squares(resid, u, bounds=(lo, hi), x_scale=scale, diff_step=1e-4, max_nfev=80, method="trf")
        if best is None or r.cost < best.cost:
            best = r
    return best


def interval_halfwidths(result, z: float = 1.96):
    """z x the standard errors of a least_squares result's parameters, from its Jacobian of residuals in
    noise units (cov = (J'J)^-1 x the residual variance per degree of freedom).  The residuals of
    neighbouring samples are correlated (a model error is smooth), so these intervals are too narrow
    by about the square root of the correlation length; None when J'J is singular."""
    J = np.asarray(result.jac, float)
    m, p = J.shape
    try:
        cov = np.linalg.inv(J.T @ J) * (2 * float(result.cost) / max(m - p, 1))
    except np.linalg.LinAlgError:     # J'J singular (a parameter the data do not move): no interval
        return None
    d = np.diag(cov)
    return np.where(d >= 0, z * np.sqrt(np.abs(d)), np.nan)


def fit_nominal(ctx: Context, mask=None) -> Fit:
    """The nominal model with its initial state fitted on ``mask`` (default: the training blocks)."""
    sim = ctx.simulator(None, (), {})
    torque = ctx.data.torque_cmd_nm
    mask = ctx.train if mask is None else mask
    n_read = periods_read(mask, ctx.data.n)

    def resid(u):
        motor, train = sim.run([], ctx.x0 + u, torque, n=n_read)
        return ctx.residuals(ctx.predict(motor, train), ctx.sigma_nom, mask)

    r = _fit_ls(resid, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), [np.zeros(2)], ctx.sigma_nom)
    x0 = ctx.x0 + r.x
    motor, train = sim.run([], x0, torque)
    pred = ctx.predict(motor, train)
    return Fit("nominal", {}, 0, pred, dict(ctx.sigma_nom), 2 * float(r.cost),
               extra={"x0": x0.tolist(), "plant_motor": motor, "plant_train": train})


@dataclass(frozen=True)
class PlantCandidate:
    """A plant-level effect; parameters fitted in log space when ``log`` (positive scale parameters)."""

    name: str
    fit_params: tuple
    lo: tuple
    hi: tuple
    log: tuple
    scan: tuple = (9,)     # coarse-scan points per parameter (log-spaced when ``log``)

    def fit(self, ctx: Context, nominal: Fit, starts: list[tuple] | None = None) -> Fit:
        """The effect fitted on ``ctx``'s training blocks: a coarse scan (``scan``), then least squares
        from its best three points and from the best with the nominal fit's start; or, given ``starts``
        ((parameter values by name, initial state) pairs; the values clipped to the range), least squares
        from those alone, no scan (a refit from where another fit landed: ``select.Forward.first_again``)."""
        fixed = fill_defaults({self.name: dict(EFFECTS[self.name].params)}, ctx.cfg)[self.name]
        sim = ctx.simulator(self.name, self.fit_params, fixed)
        torque = ctx.data.torque_cmd_nm
        np_ = len(self.fit_params)
        lo = np.array([math.log(v) if lg else v for v, lg in zip(self.lo, self.log)])
        hi = np.array([math.log(v) if lg else v for v, lg in zip(self.hi, self.log)])
        x0_nom = ctx.x0   # the measured line, not the nominal fit's (which may bend to hide the gap)

        def theta_of(u):
            return np.array([math.exp(v) if lg else v for v, lg in zip(u[:np_], self.log)])

        def resid(u):
            x0 = x0_nom + (u[np_:] if len(u) > np_ else 0.0)
            try:
                motor, train = sim.run(theta_of(u), x0, torque, n=ctx.n_read)
            except (FloatingPointError, RuntimeError):
                # the model diverges (FloatingPointError) or CasADi cannot evaluate it at these parameters:
                # a residual far worse than any fit, so the search steps back into the range it can use
                return np.full(n_res, 1e3)
            return ctx.residuals(ctx.predict(motor, train), ctx.sigma_nom, ctx.train)

        n_res = len(ctx.residuals(nominal.pred, ctx.sigma_nom, ctx.train))
        if starts is not None:
            def u_of(p):
                return np.clip([math.log(p[k]) if lg else p[k] for k, lg in zip(self.fit_params, self.log)], lo, hi)
            starts = [np.concatenate([u_of(p), np.asarray(x0, float) - ctx.x0]) for p, x0 in starts]
        else:
            # coarse scan (a grid per parameter, all combinations) to start in the right basin
            grids = [np.linspace(a, b, n) for a, b, n in zip(lo, hi, self.scan)]
            mesh = np.array(np.meshgrid(*grids, indexing="ij")).reshape(np_, -1).T
            costs = [float(np.sum(resid(u) ** 2)) for u in mesh]
            order = np.argsort(costs)
            starts = [np.concatenate([mesh[i], np.zeros(2)]) for i in order[:3]]
            starts.append(np.concatenate([mesh[order[0]], np.array(nominal.extra["x0"]) - ctx.x0]))
        best = _fit_ls(resid, None, lo, hi, np.maximum(hi - lo, 1e-9) / 10, starts, ctx.sigma_nom)
        theta = theta_of(best.x)
        x0 = x0_nom + best.x[np_:]
        motor, train = sim.run(theta, x0, torque)
        params = dict(zip(self.fit_params, map(float, theta)))
        ci, at_bound = {}, {}
        half = interval_halfwidths(best)
        for i, (name, lg) in enumerate(zip(self.fit_params, self.log)):
            u = best.x[i]
            span = hi[i] - lo[i]
            at_bound[name] = bool(u - lo[i] <= 1e-3 * span or hi[i] - u <= 1e-3 * span)
            h = half[i] if half is not None else math.nan
            lo_u, hi_u = u - h, u + h
            ci[name] = ([math.exp(lo_u), math.exp(hi_u)] if lg else [lo_u, hi_u]) if math.isfinite(h) else None
        return Fit(self.name, params, np_, ctx.predict(motor, train), dict(ctx.sigma_nom), 2 * float(best.cost),
                   extra={"plant": (self.name, dict(fixed, **params)), "x0": x0.tolist(), "param_ci": ci,
                          "at_bound": at_bound, "plant_motor": motor, "plant_train": train})


@dataclass(frozen=True)
class SensorDelayCandidate:
    """Sensors that report the plant late, in one of three forms (``form``): ``pure`` (both speed
    sensors, and so the TCU, see the plant ``delay`` late), ``low_pass`` (both filtered, first order,
    time constant ``delay``) or ``per_signal`` (the motor encoder alone ``delay`` late).  The measured
    start is then the state about ``delay`` earlier on the delayed signals, so the initial state is
    refitted with the delay."""

    name: str = "sensor_delay"
    form: str = "pure"
    param: str = "delay_ms"
    max_periods: float = 20.0

    #: form -> the Context.predict argument (and Fit.extra key) it sets
    ARGUMENT = {"pure": "sensor_delay", "low_pass": "lowpass_tau", "per_signal": "motor_delay"}

    def fit(self, ctx: Context, nominal: Fit) -> Fit:
        sim = ctx.simulator(None, (), {})
        torque = ctx.data.torque_cmd_nm
        x0_nom = ctx.x0
        T = ctx.data.period_s
        arg = self.ARGUMENT[self.form]
        # which initial-state components the delay moves (the motor alone for a per-signal delay)
        lagged = np.array([1.0, 0.0]) if self.form == "per_signal" else np.ones(2)

        def pred_of(u, n=None):
            motor, train = sim.run([], x0_nom + lagged * ctx.x0_slope * u[0] * T + u[1:], torque, n=n)
            return ctx.predict(motor, train, **{arg: u[0]}), (motor, train)

        def resid(u):
            return ctx.residuals(pred_of(u, ctx.n_read)[0], ctx.sigma_nom, ctx.train)

        grid = np.arange(0.0, self.max_periods + 1e-9, 0.5)
        costs = [float(np.sum(resid(np.array([d, 0.0, 0.0])) ** 2)) for d in grid]
        d0 = grid[int(np.argmin(costs))]
        nominal_start = np.concatenate([[0.0], np.array(nominal.extra["x0"]) - ctx.x0])   # never worse than nominal
        best = _fit_ls(resid, None, np.array([0.0]), np.array([self.max_periods]), np.array([1.0]),
                       [np.array([d0, 0.0, 0.0]), nominal_start], ctx.sigma_nom)
        pred, (motor, train) = pred_of(best.x)
        d = float(best.x[0])
        x0 = x0_nom + lagged * ctx.x0_slope * d * T + best.x[1:]
        half = interval_halfwidths(best)
        h = float(half[0]) if half is not None and math.isfinite(half[0]) else None
        return Fit(self.name, {self.param: d * T * 1e3}, 1, pred, dict(ctx.sigma_nom), 2 * float(best.cost),
                   extra={arg: d, "x0": x0.tolist(), "plant_motor": motor, "plant_train": train,
                          "at_bound": {self.param: bool(d <= 1e-3 or d >= self.max_periods - 1e-3)},
                          "param_ci": {self.param: [max(d - h, 0.0) * T * 1e3, (d + h) * T * 1e3] if h else None}})


def fit_pair(ctx: Context, plant: PlantCandidate, sensor: SensorDelayCandidate, plant_params: dict,
             delay_periods: float, x0) -> Fit:
    """A plant effect and a sensor form fitted together: their parameters and the initial state by one
    least-squares fit, from the values forward selection reached (a greedy pair is fitted one effect
    at a time: the first, fitted alone, absorbed part of the second, and one refit round does not
    undo it).  The Fit carries the sensor form's name and parameter; ``extra["plant_params"]`` the
    plant effect's."""
    fixed = fill_defaults({plant.name: dict(EFFECTS[plant.name].params)}, ctx.cfg)[plant.name]
    sim = ctx.simulator(plant.name, plant.fit_params, fixed)
    torque = ctx.data.torque_cmd_nm
    T = ctx.data.period_s
    np_ = len(plant.fit_params)
    arg = sensor.ARGUMENT[sensor.form]
    lagged = np.array([1.0, 0.0]) if sensor.form == "per_signal" else np.ones(2)
    lo = np.array([math.log(v) if lg else v for v, lg in zip(plant.lo, plant.log)] + [0.0])
    hi = np.array([math.log(v) if lg else v for v, lg in zip(plant.hi, plant.log)] + [sensor.max_periods])

    def theta_of(u):
        return np.array([math.exp(v) if lg else v for v, lg in zip(u[:np_], plant.log)])

    def start_of(u):
        return ctx.x0 + lagged * ctx.x0_slope * u[np_] * T + u[np_ + 1:]

    def resid(u):
        try:
            motor, train = sim.run(theta_of(u), start_of(u), torque, n=ctx.n_read)
        except (FloatingPointError, RuntimeError):     # as PlantCandidate.fit's: a residual worse than any fit
            return np.full(n_res, 1e3)
        return ctx.residuals(ctx.predict(motor, train, **{arg: u[np_]}), ctx.sigma_nom, ctx.train)

    u0 = np.array([math.log(plant_params[n]) if lg else plant_params[n] for n, lg in zip(plant.fit_params, plant.log)]
                  + [delay_periods])
    u0 = np.clip(u0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    n_res = len(resid(np.concatenate([u0, np.zeros(2)])))
    dx0 = np.asarray(x0, float) - start_of(np.concatenate([u0, np.zeros(2)]))
    best = _fit_ls(resid, None, lo, hi, np.maximum(hi - lo, 1e-9) / 10, [np.concatenate([u0, dx0])],
                   ctx.sigma_nom)
    theta, d = theta_of(best.x), float(best.x[np_])
    motor, train = sim.run(theta, start_of(best.x), torque)
    span = hi - lo
    at_bound = {n: bool(best.x[i] - lo[i] <= 1e-3 * span[i] or hi[i] - best.x[i] <= 1e-3 * span[i])
                for i, n in enumerate([*plant.fit_params, sensor.param])}
    return Fit(sensor.name, {sensor.param: d * T * 1e3}, np_ + 1, ctx.predict(motor, train, **{arg: d}),
               dict(ctx.sigma_nom), 2 * float(best.cost),
               extra={arg: d, "x0": start_of(best.x).tolist(), "plant_motor": motor, "plant_train": train,
                      "plant": (plant.name, dict(fixed, **dict(zip(plant.fit_params, map(float, theta))))),
                      "plant_params": dict(zip(plant.fit_params, map(float, theta))),
                      "at_bound": at_bound, "param_ci": {}})


def plant_side(pair: Fit, plant: PlantCandidate) -> Fit:
    """A ``fit_pair`` result named after its plant effect (its parameters and at-bound flags), for a ranking
    row where the plant effect is the one being judged."""
    return Fit(plant.name, pair.extra["plant_params"], pair.k, pair.pred, pair.sigma, pair.train_cost,
               extra={**pair.extra, "at_bound": {k: v for k, v in pair.extra["at_bound"].items()
                                                 if k in plant.fit_params}})


def match_frames(tcu_creep, sensor_creep, max_back: int = 40) -> tuple[np.ndarray, float]:
    """For each TCU period k, the sensor frame j(k) <= k whose creep the TCU used (the newest exact
    copy in the last ``max_back`` frames), and the fraction of periods with an exact copy."""
    n = len(sensor_creep)
    idx = np.arange(n)[:, None] - np.arange(max_back + 1)[None, :]      # k, k-1, ..., k-max_back
    valid = idx >= 0
    cand = sensor_creep[np.clip(idx, 0, n - 1)]
    diff = np.abs(cand - tcu_creep[:, None])
    diff[~valid] = np.inf
    exact = diff <= 1e-12 * np.maximum(1.0, np.abs(tcu_creep[:, None]))
    has = exact.any(axis=1) & np.isfinite(tcu_creep)
    back = np.where(has, np.argmax(exact, axis=1), np.argmin(np.nan_to_num(diff, nan=np.inf), axis=1))
    j = np.arange(n) - back
    return j, float(has.mean())


@dataclass(frozen=True)
class CanCandidate:
    """The TCU's inputs are the sensor frames, late (CAN delay, jitter) or repeated (loss).

    The TCU's logged creep is computed from the frame it used, so where it is an exact copy of a
    sensor frame's creep, that frame is known: the fit is the frame map j(k), summarised as the mean
    delay, its spread, and the fraction of repeated frames.  Without exact copies (frames re-scaled
    on a real bus), a single fractional delay is fitted instead.
    """

    name: str = "can"
    max_periods: float = 20.0

    def fit(self, ctx: Context, nominal: Fit) -> Fit:
        d = ctx.data
        T = d.period_s
        motor, train = nominal.extra["plant_motor"], nominal.extra["plant_train"]
        sensor_creep = ctx.observer.creep_kmh(d.motor_speed_rad_s, d.train_speed_ms)
        j, exact = match_frames(np.asarray(d.tcu_creep_kmh, float), sensor_creep)
        ok = np.isfinite(d.tcu_creep_kmh[1:]) & np.isfinite(d.tcu_creep_kmh[:-1])
        repeats = float(np.mean(d.tcu_creep_kmh[1:][ok] == d.tcu_creep_kmh[:-1][ok])) if ok.any() else 0.0
        if exact >= 0.9:
            lag = (np.arange(d.n) - j)[ctx.window]
            pred = {"motor": motor, "train": train,
                    "mu_hat": ctx.observer.mu_hat(motor[j], d.torque_cmd_nm)}
            params = {"delay_ms": float(lag.mean() * T * 1e3),
                      "delay_spread_ms": float((np.quantile(lag, 0.95) - np.quantile(lag, 0.05)) * T * 1e3),
                      "repeat_fraction": repeats}
            note = (f"{exact * 100:.1f} % of TCU readings are exact copies of sensor frames; {repeats * 100:.1f} % "
                    f"repeat the previous one (lost or late frames)")
            extra = {"can_frames": j}
        else:
            def cost(dl):
                pr = ctx.predict(motor, train, can_delay=dl)
                return float(np.sum(ctx.residuals(pr, ctx.sigma_nom, ctx.train) ** 2))

            grid = np.arange(0.0, self.max_periods + 1e-9, 0.5)
            costs = [cost(g) for g in grid]
            i = int(np.argmin(costs))
            r = minimize_scalar(cost, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]),
                                method="bounded", options={"xatol": 1e-3})
            dl = float(r.x) if r.fun < costs[i] else float(grid[i])
            pred = ctx.predict(motor, train, can_delay=dl)
            params = {"delay_ms": dl * T * 1e3, "delay_spread_ms": 0.0, "repeat_fraction": repeats}
            note = "TCU readings are not exact copies of sensor frames: one fractional delay fitted"
            extra = {"can_delay": dl}
        extra["x0"] = nominal.extra["x0"]
        return Fit(self.name, params, 3, pred, dict(ctx.sigma_nom), math.nan, note, extra)


def quantised_expectation(m, q: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(E, Var) of round((m + n) / q) * q with n ~ N(0, sigma^2), elementwise: a smoothed staircase."""
    from scipy.special import ndtr

    s = max(sigma, 1e-12)
    k0 = np.round(m / q)
    ks = k0[:, None] + np.arange(-4, 5)[None, :]
    p = ndtr(((ks + 0.5) * q - m[:, None]) / s) - ndtr(((ks - 0.5) * q - m[:, None]) / s)
    e = q * np.sum(p * ks, axis=1)
    v = np.maximum(q * q * np.sum(p * ks * ks, axis=1) - e * e, 0.0)
    return e, v


@dataclass(frozen=True)
class QuantisationCandidate:
    """Speed sensors quantised.  The quantum comes from the lattice the measured values sit on; the
    prediction is the expected quantised value of the nominal model's speed plus the sensor noise
    (a staircase, smoothed by the noise), and the noise floor the quantiser's variance around it."""

    name: str = "sensor_quantisation"

    def fit(self, ctx: Context, nominal: Fit) -> Fit:
        sig = dict(ctx.sigma_nom)
        pred = dict(nominal.pred)
        params = {}
        notes = []
        plant = {"motor": nominal.extra["plant_motor"], "train": nominal.extra["plant_train"]}
        quanta = {}
        for s, key, floor in (("motor", "motor_quantum_rad_s", 1e-3), ("train", "train_quantum_ms", 1e-4)):
            base = ctx.sigma_nom[s]
            y = ctx.meas[s][ctx.train & ctx.valid[s]]
            q, coh = lattice_quantum(y, max(2 * base, floor), max(400 * base, 100 * floor))
            params[key] = q if coh > 0.9 else 0.0
            if coh > 0.9:
                quanta[s] = q
                notes.append(f"{s} values on a {q:.4g} lattice (coherence {coh:.3f})")
        x0 = np.array(nominal.extra["x0"])
        if quanta:
            # the staircase needs the trajectory to a fraction of a quantum: refit the initial state on it
            sim = ctx.simulator(None, (), {})
            torque = ctx.data.torque_cmd_nm

            def stair(u, n=None):
                motor, train = sim.run([], ctx.x0 + u, torque, n=n)
                out = {"motor": motor, "train": train}
                for sg, q in quanta.items():
                    out[sg] = quantised_expectation(out[sg], q, ctx.sigma_nom[sg])[0]
                return out, (motor, train)

            def resid(u):
                out = stair(u, ctx.n_read)[0]
                n = ctx.n_read
                return np.concatenate([(ctx.meas[sg][:n] - out[sg])[ctx.train[:n]] / ctx.sigma_nom[sg]
                                       for sg in ("motor", "train")])

            r = _fit_ls(resid, None, np.zeros(0), np.zeros(0), np.zeros(0), [np.array(nominal.extra["x0"]) - ctx.x0],
                        ctx.sigma_nom)
            x0 = ctx.x0 + r.x
            _, (pm, pt) = stair(r.x)
            plant = {"motor": pm, "train": pt}
            pred.update(motor=pm, train=pt, mu_hat=ctx.observer.mu_hat(pm, torque))
        for sg, q in quanta.items():
            e, v = quantised_expectation(plant[sg], q, ctx.sigma_nom[sg])
            pred[sg] = e
            sig[sg] = float(np.sqrt(np.mean(v[ctx.window])))
        q = params.get("motor_quantum_rad_s", 0.0)
        if q > 0:
            # mu^ of the expected staircase; its floor from seeded draws of quantised noisy speeds
            torque = ctx.data.torque_cmd_nm
            pred["mu_hat"] = ctx.observer.mu_hat(pred["motor"], torque)
            rng = np.random.default_rng(99)
            m = plant["motor"]
            sq = []
            for _ in range(4):
                noisy = m + ctx.sigma_nom["motor"] * rng.standard_normal(m.size)
                mu_q = ctx.observer.mu_hat(np.round(noisy / q) * q, torque)
                sq.append(np.mean((mu_q - pred["mu_hat"])[ctx.window] ** 2))
            sig["mu_hat"] = float(np.sqrt(np.mean(sq)))
        return Fit(self.name, params, 1, pred, sig, math.nan, "; ".join(notes),
                   {"quanta": params, "x0": x0.tolist()})


def from_record(name: str):
    """The candidate of effect ``name``, built from its record's fit settings (``hil.effects``)."""
    spec = EFFECTS[name]
    fit = spec.fit
    if isinstance(fit, PlantFit):
        return PlantCandidate(name, fit.params, fit.lo, fit.hi, fit.log, fit.scan)
    if isinstance(fit, DelayFit):
        return SensorDelayCandidate(name, fit.form, fit.param, fit.max_periods)
    if fit == "quantiser":
        return QuantisationCandidate(name)
    if fit == "frames":
        return CanCandidate(name)
    raise ValueError(f"effect {name!r}: no fit settings the diagnosis knows ({fit!r})")


#: the nuisance fitted before any effect is compared: the rail's fault curve, scaled in mu and in creep
RAIL = from_record("rail_curve")


def _order(spec) -> tuple:
    """The candidate list's order: the least-squares fits first (each class's own form, then the other
    forms), the quantiser's and the frame map's last; the registry's order within each."""
    return (not isinstance(spec.fit, (PlantFit, DelayFit)), bool(spec.cls))


def candidates(scenario, exclude=()) -> list:
    """The candidate list the diagnosis tries: every effect whose record says ``candidate``, one
    candidate per form, built from the record's fit settings (``from_record``), but the effects named
    in ``exclude`` (the blind bench holds the truth's own form out)."""
    specs = sorted((s for s in EFFECTS.values() if s.candidate), key=_order)
    return [from_record(s.name) for s in specs if s.name not in exclude]
