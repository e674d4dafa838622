"""What the strategies that model the motor speed itself (``bayes``, ``gp``) share: the readings
before the slip (the sensor's noise and the train speed, ``BaselineStats``), the creep they use, and
the sample loop (the slip's first sample opens the model, each later one steps it, every one is
evaluated), and the confirmation's tolerance test (``within_tolerance``).  Why readings before the slip: the likelihood's scale is then the sensor's, measured,
not a tuning knob, and the creep uses a smoothed train speed instead of a noisy one."""
from __future__ import annotations

import math

import numpy as np

from ..messages import IdentificationEvent
from .base import Sample, Strategy, load_kernels

KMH_PER_MS = 3.6


class BaselineStats:
    """What the readings before the slip tell: the motor-speed noise (second differences) and the
    train speed as a straight line in the step (least squares over the last ``size`` readings).
    The readings go into ring buffers (a few stores per reading); the statistics are computed once,
    at the slip's first sample, on ``size`` numbers."""

    def __init__(self, size: int):
        self.size = size
        self._buf = np.zeros((3, size))        # step, motor speed, train speed
        self.count = 0

    def add(self, step: int, motor_speed_rad_s: float, train_speed_ms: float) -> None:
        i = self.count % self.size
        buf = self._buf
        buf[0, i], buf[1, i], buf[2, i] = step, motor_speed_rad_s, train_speed_ms
        self.count += 1

    def _ordered(self, row: int) -> np.ndarray:
        """The buffer's row ``row``, oldest reading first."""
        n = min(self.count, self.size)
        i = self.count % self.size
        x = self._buf[row]
        return x[:n] if self.count <= self.size else np.concatenate([x[i:], x[:i]])

    def stats(self, compiled: bool) -> tuple[float, tuple[float, float, float]]:
        """(motor-speed noise, train-speed line): ``motor_noise_rad_s`` and ``train_speed_line``, by
        ``kernels.baseline_stats`` when ``compiled`` (one call instead of two dozen numpy ones)."""
        if self.count < 2:
            return math.nan, (self._buf[0, 0], self._buf[2, 0] if self.count else math.nan, 0.0)
        if compiled:
            sigma, k0, v0, slope = load_kernels().baseline_stats(self._buf, self.count)
            return sigma, (k0, v0, slope)
        return self.motor_noise_rad_s(), self.train_speed_line()

    def motor_noise_rad_s(self) -> float:
        y = self._ordered(1)
        if y.size < 8:
            return math.nan
        d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
        return float(np.sqrt(np.mean(d2 * d2) / 6.0))

    def train_speed_line(self) -> tuple[float, float, float]:
        """(step0, v at step0, slope per step) of the least-squares line through the last readings."""
        k, v = self._ordered(0), self._ordered(2)
        if k.size < 2:
            return (k[-1] if k.size else 0.0), (v[-1] if v.size else math.nan), 0.0
        k0 = float(k.mean())
        dk = k - k0
        slope = float(dk @ (v - v.mean()) / max(dk @ dk, 1e-12))
        return k0, float(v.mean()), slope


class SpeedModelStrategy(Strategy):
    """The sample loop of a strategy that models the motor speed: a subclass sets ``baseline`` (a
    ``BaselineStats``) and ``_compiled`` in its constructor and defines ``_open``, ``_step`` and
    ``_evaluate``.  Every sample it takes is kept in ``samples_seen`` (the offline oracle of ``hil
    bench identify`` replays them)."""

    observer_aware = True           # every sample from the detected slip start, no settle, no lag pairing
    wants_readings = True           # TractionIdentifier.on_sensor passes every reading to ``on_reading``

    def __init__(self, settings, seed: int = 0):
        super().__init__(settings, seed)
        veh = settings.vehicle
        self.period_s = settings.period_s
        self.creep_per_motor_speed = KMH_PER_MS * veh.wheel_radius_m / veh.gear_ratio   # km/h per rad/s
        self.baseline: BaselineStats | None = None
        self._compiled = False
        self._prev: Sample | None = None
        self._line = None
        self.samples_seen: list[Sample] = []

    def merged_options(self) -> dict:
        """The class's ``defaults`` with the scenario's ``[identifier.options.NAME]`` over them; an
        unknown key is refused by name."""
        unknown = set(self.options) - set(self.defaults) - {"window_samples", "k_pe", "c_lw", "c_up"}
        if unknown:
            raise ValueError(f"{self.name}: unknown option(s) {', '.join(sorted(unknown))}")
        return {**self.defaults, **self.options}

    def event(self, s: Sample, kind: str, theta, peak_mu_ci, peak_creep_ci, peak_open: bool = False,
              samples_from_s: float = math.nan) -> IdentificationEvent:
        """The event of ``kind`` (correction, confirmed, unconfirmed) with the curve and its intervals
        (``peak_open``: their upper ends are the working range's, not the data's) and the span of the samples it
        rests on, ``samples_from_s`` to this sample's time (NaN: not stated); the strategy's state follows it
        (``confirmed``, ``gave_up``, ``corrections``)."""
        self.theta, self.peak_mu_ci, self.peak_creep_ci = np.asarray(theta, float), peak_mu_ci, peak_creep_ci
        if kind == "confirmed":
            self.confirmed = True
        elif kind == "unconfirmed":
            self.gave_up = True
        else:
            self.corrections += 1
        return IdentificationEvent(s.step, s.t_s, kind, self.corrections, tuple(float(x) for x in self.theta),
                                   math.nan, len(self._v), self.peak_mu_ci, self.peak_creep_ci, bool(peak_open),
                                   float(samples_from_s), s.t_s if math.isfinite(samples_from_s) else math.nan)

    def on_reading(self, step: int, motor_speed_rad_s: float, train_speed_ms: float) -> None:
        """Every reading before the slip: the baseline of the noise and of the train speed."""
        if self._prev is None:
            self.baseline.add(step, motor_speed_rad_s, train_speed_ms)

    def creep_for_likelihood(self, s: Sample) -> float:
        """v_s from the measured motor speed and the smoothed train speed (km/h)."""
        k0, v0, slope = self._line
        return self.creep_per_motor_speed * s.motor_speed_rad_s - KMH_PER_MS * (v0 + slope * (s.step - k0))

    def open_baseline(self, s: Sample, sigma_fallback: float) -> float:
        """At the slip's first sample: the baseline is final; sets the train-speed line and returns
        the motor-speed noise (``sigma_fallback`` when there were too few readings)."""
        sigma_y, line = self.baseline.stats(self._compiled)
        self._line = line if self.baseline.count else (s.step, s.train_speed_ms, 0.0)
        return sigma_y if math.isfinite(sigma_y) and sigma_y > 0 else float(sigma_fallback)

    def add_sample(self, sample: Sample) -> list[IdentificationEvent]:
        if self.confirmed or self.gave_up:
            return []
        if not all(math.isfinite(x) for x in (sample.creep_speed_kmh, sample.motor_speed_rad_s, sample.train_speed_ms,
                                               sample.torque_nm)):
            return []           # (mu^ is not used: it is kept for the paper's fit metrics only)
        self._v.append(sample.creep_speed_kmh)
        self._mu.append(sample.mu_hat)
        self.samples_seen.append(sample)
        if self._prev is None:
            self._open(sample)
        else:
            self._step(sample)
        self._prev = sample
        return self._evaluate(sample)

    def _open(self, s: Sample) -> None:
        raise NotImplementedError

    def _step(self, s: Sample) -> None:
        raise NotImplementedError

    def _evaluate(self, s: Sample) -> list[IdentificationEvent]:
        raise NotImplementedError

    def correct(self, window_v, window_mu):          # the window loop of Strategy is not used here
        raise NotImplementedError


def within_tolerance(lo: float, estimate: float, hi: float, tol: float) -> bool:
    """Every value of [lo, hi] would find ``estimate`` within ``tol`` of itself (relative): lo >=
    estimate / (1 + tol) and hi <= estimate / (1 - tol).  So when the truth is in the interval, the
    estimate is correct by the bench's own measure (|estimate - truth| <= tol truth)."""
    return estimate > 0 and lo >= estimate / (1.0 + tol) and hi <= estimate / (1.0 - tol)
