"""A drill that keeps the identification's code warm while the TCU only monitors.

The identifier's costliest samples after a fault are not its heaviest arithmetic but code that has
not run for a while: before the fault the TCU runs only the observer and the slip detector, so by
the fault the strategy's Python paths and compiled kernels have left the CPU's caches, and the
first samples of an identification cost several times what the same work costs warm (measured
with ``hil bench identify``: docs/design/identification.md).

So, while monitoring (and, for strategies fed from the slip's settled samples, through the settle
time after a detection), every reading also feeds one sample of a synthetic slip to a small copy of
the strategy (its ``drill_size_option`` set to ``drill_particles``, at least its
``drill_size_min``: particles, or a ``gp``'s posterior draws; its own random generator): the same
code runs on a few kilobytes of data, once per sample, so it is warm when the real slip comes.  A
strategy that models the motor speed (``wants_readings``) gets a slip of speed readings, made by
integrating the wheelset J dw/dt = T - c mu(v_s) on the prior curve (Euler, ``_SUBSTEPS`` per
period) under a torque 6 % above its peak, after ``DRILL_BASELINE`` readings before the slip; the
others get (creep, mu) samples on the prior curve.  The drill shares nothing mutable with the real
strategy, so the real identification's results are the same with or without it; only its cost
changes.

A drill that has confirmed (or run out of samples) starts again from a template built up front,
copied a few attributes per reading (``_RESTART_ATTRIBUTES``), so no reading carries a whole
strategy's construction.
"""
from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np

from .curve import mu_model, peak
from .strategies import STRATEGIES, Sample, make_strategy

#: the synthetic slip: creep speeds (km/h) the drill's samples span, their count, and the noise
#: (mu units) on the prior curve, enough for the confidence check to pass as on real samples
DRILL_CREEP_KMH = (0.5, 0.9)
DRILL_SAMPLES = 60
DRILL_NOISE_STD = 0.001
#: the speed slip (strategies that model the motor speed): readings before it, the most samples,
#: the highest creep as a multiple of the prior curve's peak creep, the train speed, the noise of
#: the motor-speed readings, the torque over the curve's peak and the integration's sub-steps
DRILL_BASELINE = 100
DRILL_SPEED_SAMPLES = 200
DRILL_CREEP_OVER_PEAK = (0.3, 2.5)
DRILL_TRAIN_SPEED_MS = 10.0
DRILL_SPEED_NOISE_RAD_S = 0.005
DRILL_TORQUE_OVER_PEAK = 1.06
_SUBSTEPS = 10
#: attributes copied from the template per reading while the drill restarts (spread over readings)
_RESTART_ATTRIBUTES = 16


class Drill:
    """``tick()`` once per reading: one synthetic sample into a small copy of ``strategy``.

    ``error``: None, or why the drill stopped (it never raises into the TCU's loop).
    """

    def __init__(self, settings, strategy: str, particles: int, seed: int = 0):
        options = {k: dict(v) if isinstance(v, dict) else v for k, v in settings.options.items()}
        mine = options.setdefault(strategy, {})
        cls = STRATEGIES[strategy]
        mine[cls.drill_size_option] = max(int(particles), cls.drill_size_min)
        self.settings = dataclasses.replace(settings, options=options)
        self._template = make_strategy(strategy, self.settings, seed)
        rng = np.random.default_rng(seed)
        if getattr(self._template, "wants_readings", False):
            pre, self._samples = speed_slip(settings, rng)
            for step, motor_speed_rad_s, train_speed_ms in pre:
                self._template.on_reading(step, motor_speed_rad_s, train_speed_ms)
        else:
            theta = np.asarray(settings.initial_guess, float)
            creep = np.linspace(*DRILL_CREEP_KMH, DRILL_SAMPLES)
            mu = mu_model(creep, theta) + rng.normal(0.0, DRILL_NOISE_STD, creep.size)
            period = settings.period_s
            self._samples = [Sample(k, k * period, float(v), float(m)) for k, (v, m) in enumerate(zip(creep, mu))]
        self.strategy = None
        self._next = 0
        self._restart: list | None = None     # (new object, remaining template items) while restarting
        self.cycles = 0                       # identifications the drill finished (confirmed, gave up or ran out)
        self.error: str | None = None

    def tick(self) -> None:
        if self.error is not None:
            return
        try:
            s = self.strategy
            if s is None or s.confirmed or s.gave_up or self._next >= len(self._samples):
                self._restart_step()
                return
            s.add_sample(self._samples[self._next])
            self._next += 1
        except Exception as e:      # a warm-up aid: never let it stop the TCU; say why it stopped
            self.error = f"{type(e).__name__}: {e}"
            self.strategy = self._restart = None

    def _restart_step(self) -> None:
        if self._restart is None:
            if self.strategy is not None:
                self.cycles += 1
            self.strategy = None
            self._restart = [object.__new__(type(self._template)), list(self._template.__dict__.items())]
        new, items = self._restart
        for key, value in items[:_RESTART_ATTRIBUTES]:
            new.__dict__[key] = _copy(value)
        del items[:_RESTART_ATTRIBUTES]
        if not items:
            self.strategy, self._restart, self._next = new, None, 0


def speed_slip(settings, rng) -> tuple[list, list]:
    """(readings before the slip as (step, motor speed, train speed), the slip's samples): the
    wheelset on the prior curve (``initial_guess``) under a torque ``DRILL_TORQUE_OVER_PEAK`` times
    its peak's, from ``DRILL_CREEP_OVER_PEAK``[0] to [1] times its peak creep."""
    veh, dt = settings.vehicle, settings.period_s
    theta = np.asarray(settings.initial_guess, float)
    peak_creep_kmh, peak_mu = peak(theta)
    kmh_per_rad_s = 3.6 * veh.wheel_radius_m / veh.gear_ratio
    train_kmh = 3.6 * DRILL_TRAIN_SPEED_MS
    torque_nm = DRILL_TORQUE_OVER_PEAK * peak_mu * veh.torque_per_mu_nm
    omega = (DRILL_CREEP_OVER_PEAK[0] * peak_creep_kmh + train_kmh) / kmh_per_rad_s
    noise = DRILL_SPEED_NOISE_RAD_S * rng.standard_normal(DRILL_BASELINE + DRILL_SPEED_SAMPLES)
    pre = [(k, omega + noise[k], DRILL_TRAIN_SPEED_MS) for k in range(DRILL_BASELINE)]
    samples = []
    for k in range(DRILL_BASELINE, DRILL_BASELINE + DRILL_SPEED_SAMPLES):
        y = omega + noise[k]
        creep_kmh = kmh_per_rad_s * y - train_kmh
        samples.append(Sample(k, k * dt, creep_kmh, math.nan, math.nan, y, DRILL_TRAIN_SPEED_MS, torque_nm))
        if creep_kmh > DRILL_CREEP_OVER_PEAK[1] * peak_creep_kmh:
            break
        for _ in range(_SUBSTEPS):          # J dw/dt = T - c mu(v_s)
            mu = float(mu_model(np.array([kmh_per_rad_s * omega - train_kmh]), theta)[0])
            omega += dt / _SUBSTEPS * (torque_nm - veh.torque_per_mu_nm * mu) / veh.equivalent_inertia_kgm2
    return pre, samples


def _copy(value):
    """A copy deep enough for a strategy's state: arrays and containers copied, our own objects
    (e.g. the prelim's lattice) attribute by attribute; settings, option dicts and the random
    generator shared (the drill only reads the first two; its draws need not repeat)."""
    t = type(value)
    if t is np.ndarray:
        return value.copy()
    if t is list:
        return [_copy(x) for x in value]
    if t is collections.deque:
        return collections.deque(_copy(x) for x in value)
    if t.__module__.startswith("identifier.") and hasattr(value, "__dict__") and not dataclasses.is_dataclass(value):
        new = object.__new__(t)
        new.__dict__.update({k: _copy(v) for k, v in value.__dict__.items()})
        return new
    return value
