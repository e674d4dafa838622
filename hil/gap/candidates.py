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

from plant.reality import EFFECTS, fill_defaults

from .model import Simulator, lattice_quantum, shift

SIGNALS = ("motor", "train", "mu_hat")
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
        self.train = train_mask
        self.held = held_mask
        self.sigma_nom = sigma_nom
        self.meas = {"motor": data.motor_speed_rad_s, "train": data.train_speed_ms, "mu_hat": data.tcu_mu_hat}
        self.valid = {s: np.isfinite(v) for s, v in self.meas.items()}
        self.mu_gain = observer.noise_gain()
        self._sims = {}

    def simulator(self, effect, fit_params, fixed):
        key = (effect, fit_params)
        if key not in self._sims:
            self._sims[key] = Simulator(self.cfg, effect, fit_params, fixed, self.data.n)
        return self._sims[key]

    def predict(self, motor, train, sensor_delay=0.0, can_delay=0.0) -> dict:
        """Measured-signal predictions from the plant trajectory: sensors see it ``sensor_delay`` periods
        late; the TCU sees the sensor values another ``can_delay`` periods late."""
        m_s, t_s = shift(motor, sensor_delay), shift(train, sensor_delay)
        m_tcu = shift(m_s, can_delay)
        return {"motor": m_s, "train": t_s, "mu_hat": self.observer.mu_hat(m_tcu, self.data.torque_cmd_nm)}

    def residuals(self, pred: dict, sigma: dict, mask) -> np.ndarray:
        out = []
        for s in SIGNALS:
            sel = mask & self.valid[s]
            out.append((self.meas[s][sel] - pred[s][sel]) / sigma[s])
        return np.concatenate(out)


# -- candidates --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlantCandidate:
    """A plant-level effect; parameters fitted in log space when ``log`` (positive scale parameters)."""

    name: str
    fit_params: tuple
    lo: tuple
    hi: tuple
    log: tuple
    scan: int = 9

    def fit(self, ctx: Context) -> Fit:
        fixed = fill_defaults({self.name: dict(EFFECTS[self.name].params)}, ctx.cfg)[self.name]
        sim = ctx.simulator(self.name, self.fit_params, fixed)
        torque = ctx.data.torque_cmd_nm
        lo = np.array([math.log(v) if lg else v for v, lg in zip(self.lo, self.log)])
        hi = np.array([math.log(v) if lg else v for v, lg in zip(self.hi, self.log)])

        def theta_of(u):
            return np.array([math.exp(v) if lg else v for v, lg in zip(u, self.log)])

        def resid(u):
            try:
                motor, train = sim.run(theta_of(u), ctx.x0, torque)
            except (FloatingPointError, RuntimeError):
                return np.full(n_res, 1e3)
            return ctx.residuals(ctx.predict(motor, train), ctx.sigma_nom, ctx.train)

        n_res = len(ctx.residuals(ctx.predict(ctx.data.motor_speed_rad_s, ctx.data.train_speed_ms),
                                  ctx.sigma_nom, ctx.train))
        # coarse scan (a grid per parameter, all combinations) to start in the right basin
        grids = [np.linspace(a, b, self.scan if len(self.fit_params) == 1 else 5) for a, b in zip(lo, hi)]
        mesh = np.array(np.meshgrid(*grids, indexing="ij")).reshape(len(grids), -1).T
        costs = [float(np.sum(resid(u) ** 2)) for u in mesh]
        order = np.argsort(costs)
        best = None
        for i in order[:2]:
            r = least_squares(resid, mesh[i], bounds=(lo, hi), x_scale=np.maximum(hi - lo, 1e-9) / 10,
                              diff_step=1e-3, max_nfev=60, method="trf", loss="linear")
            if best is None or r.cost < best.cost:
                best = r
        theta = theta_of(best.x)
        motor, train = sim.run(theta, ctx.x0, torque)
        return Fit(self.name, dict(zip(self.fit_params, map(float, theta))), len(self.fit_params),
                   ctx.predict(motor, train), dict(ctx.sigma_nom), 2 * float(best.cost),
                   extra={"plant": (self.name, dict(fixed, **dict(zip(self.fit_params, map(float, theta)))))})


@dataclass(frozen=True)
class DelayCandidate:
    """``sensor_delay`` (both sensor signals and the TCU late) or ``can`` (only the TCU's inputs late)."""

    name: str
    max_periods: float = 20.0

    def fit(self, ctx: Context, nominal: dict) -> Fit:
        key = "sensor_delay" if self.name == "sensor_delay" else "can_delay"
        sim = ctx.simulator(None, (), {})
        cache = {}

        def plant(d):
            """The plant trajectory: for a sensor delay, the measured start is the state d periods
            earlier, so the model starts from the measured line at t = +d."""
            if key != "sensor_delay" or d == 0:
                return nominal["plant_motor"], nominal["plant_train"]
            if d not in cache:
                x0 = ctx.x0 + ctx.x0_slope * d * ctx.data.period_s
                cache.clear()
                cache[d] = sim.run([], x0, ctx.data.torque_cmd_nm)
            return cache[d]

        def cost(d):
            pred = ctx.predict(*plant(d), **{key: d})
            return float(np.sum(ctx.residuals(pred, ctx.sigma_nom, ctx.train) ** 2))

        grid = np.arange(0.0, self.max_periods + 1e-9, 0.5)
        costs = [cost(d) for d in grid]
        i = int(np.argmin(costs))
        a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        r = minimize_scalar(cost, bounds=(a, b), method="bounded", options={"xatol": 1e-3})
        d = float(r.x) if r.fun < costs[i] else float(grid[i])
        period_ms = ctx.data.period_s * 1e3
        extra = {key: d}
        motor, train = plant(d)
        pred = ctx.predict(motor, train, **extra)
        if key == "sensor_delay":
            extra["x0"] = (ctx.x0 + ctx.x0_slope * d * ctx.data.period_s).tolist()
        note = ""
        if self.name == "can":
            # readings the TCU used twice: frames lost or overtaken (exact repeats of the creep value)
            c = ctx.data.tcu_creep_kmh
            ok = np.isfinite(c[1:]) & np.isfinite(c[:-1])
            repeats = float(np.mean(c[1:][ok] == c[:-1][ok])) if ok.any() else 0.0
            note = f"{repeats * 100:.1f} % of TCU readings repeat the previous one (lost or late frames)"
            extra["repeat_fraction"] = repeats
        return Fit(self.name, {"delay_ms": d * period_ms}, 1, pred, dict(ctx.sigma_nom), cost(d), note, extra)


@dataclass(frozen=True)
class QuantisationCandidate:
    name: str = "sensor_quantisation"

    def fit(self, ctx: Context, nominal: dict) -> Fit:
        sig = dict(ctx.sigma_nom)
        params = {}
        notes = []
        for s, key, floor in (("motor", "motor_quantum_rad_s", 1e-3), ("train", "train_quantum_ms", 1e-4)):
            base = ctx.sigma_nom[s]
            y = ctx.meas[s][ctx.train & ctx.valid[s]]
            q, coh = lattice_quantum(y, max(4 * base, floor), max(400 * base, 100 * floor))
            if coh > 0.9:
                params[key] = q
                sig[s] = math.sqrt(base ** 2 + q ** 2 / 12)
                notes.append(f"{s} values on a {q:.4g} lattice (coherence {coh:.3f})")
            else:
                params[key] = 0.0
        sig["mu_hat"] = ctx.mu_gain * sig["motor"]
        q = params.get("motor_quantum_rad_s", 0.0)
        if q > 0:
            # a quantiser's error is not white (a slow signal keeps it for many samples): measure what it
            # does to mu^ by quantising the model's own speed plus seeded sensor noise
            rng = np.random.default_rng(99)
            m = nominal["motor"]
            noisy = m + ctx.sigma_nom["motor"] * rng.standard_normal(m.size)
            mu_q = ctx.observer.mu_hat(np.round(noisy / q) * q, ctx.data.torque_cmd_nm)
            sel = ctx.window
            sig["mu_hat"] = float(np.sqrt(np.mean((mu_q - nominal["mu_hat"])[sel] ** 2)))
        return Fit(self.name, params, 1, {k: nominal[k] for k in SIGNALS}, sig, math.nan, "; ".join(notes),
                   {"quanta": params})


def candidates(scenario) -> list:
    """The candidate list the diagnosis tries (every EffectSpec with candidate=True)."""
    out = [
        PlantCandidate("load_transfer", ("bogie_height_m",), (0.0,), (6.0,), (False,)),
        PlantCandidate("torque_lag", ("tau_s",), (2e-4,), (0.1,), (True,)),
        PlantCandidate("compliance", ("stiffness_nm_rad", "damping_ratio"), (2e4, 0.005), (5e6, 1.0), (True, True)),
        PlantCandidate("adhesion_lag", ("tau_s",), (2e-4,), (0.2,), (True,)),
        PlantCandidate("resistance", ("factor",), (0.0,), (5.0,), (False,)),
        DelayCandidate("sensor_delay"),
        QuantisationCandidate(),
        DelayCandidate("can"),
    ]
    assert {c.name for c in out} == {n for n, s in EFFECTS.items() if s.candidate}
    return out
