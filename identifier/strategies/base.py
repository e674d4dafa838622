"""The interface every identification strategy offers, and the window loop they share.

A strategy is fed samples one at a time (``add_sample``) and returns the events it produced:
``correction`` after each correction Q and ``confirmed`` once the multi-level evaluation accepts
a curve.  The window bookkeeping (L samples per correction, the confidence check on the next
window) lives here; a strategy only says how one correction is made (``correct``).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ..evaluation import inside_confidence_band, j_ef, standard_error
from ..curve import peak_two_terms
from ..pf import weighted_interval
from ..messages import NAN_INTERVAL, IdentificationEvent
from ..settings import IdentifierSettings


_kernels = None


def load_kernels():
    """identifier.kernels (the strategies' compiled twins), imported on first use: numba's import costs ~0.2 s,
    paid only where a compiled strategy is built."""
    global _kernels
    if _kernels is None:
        from .. import kernels
        _kernels = kernels
    return _kernels


@dataclass(frozen=True)
class Sample:
    step: int
    t_s: float
    creep_speed_kmh: float
    mu_hat: float
    speed_innovation_rad_s: float = math.nan   # y(k) - omega^(k) before the observer update (observer-aware strategies)
    motor_speed_rad_s: float = math.nan        # the reading itself (strategies that model the speed: bayes)
    train_speed_ms: float = math.nan
    torque_nm: float = math.nan                # the command answering this reading (held until the next)


#: the level of the intervals every event publishes
REPORT_LEVEL = 0.90


def cloud_peak_intervals(thetas: np.ndarray, weights: np.ndarray, level: float):
    """Peak mu and peak creep intervals of a weighted cloud of curves (N, 5) (closed-form peaks)."""
    v, mu = peak_two_terms(thetas)
    return weighted_interval(mu, weights, level), weighted_interval(v, weights, level)


class Strategy(ABC):
    """Feed samples with ``add_sample``; read ``theta``, ``confirmed``, ``corrections``."""

    name: str = ""
    #: True: the TCU feeds every sample from the detected slip start on, creep of the same instant
    #: (no settle time, no lag pairing): for strategies that model the observer's transient
    observer_aware: bool = False
    #: True: every sample's work is small (no whole-data refit), so a TractionIdentifier may run a
    #: small copy of this strategy on a synthetic slip while monitoring (identifier/drill.py)
    keeps_warm: bool = False
    #: the option the drill sets to ``drill_particles`` (at least ``drill_size_min``) to make its copy small
    drill_size_option: str = "particles"
    drill_size_min: int = 2
    #: set by the TCU: True when a control law (not the open-loop demand) acts on the wheel, so the
    #: rail may change under a slip's samples (``gp`` then dates the change; the others ignore it)
    closed_loop: bool = False

    def __init__(self, settings: IdentifierSettings, seed: int = 0):
        self.settings = settings
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.theta = np.array(settings.initial_guess, dtype=float)
        # per-strategy overrides of the shared evaluation constants: settings.options[name][key]
        self.options = dict(settings.options.get(self.name, {})) if isinstance(settings.options, dict) else {}
        self.window_samples = int(self.options.get("window_samples", settings.window_samples))   # L
        self.k_pe = float(self.options.get("k_pe", settings.k_pe))                                # K_PE
        self.c_lw = float(self.options.get("c_lw", settings.c_lw))
        self.c_up = float(self.options.get("c_up", settings.c_up))
        n = (len(self.theta) - 1) // 2
        if self.window_samples < 2 * n + 2:
            raise ValueError(f"{self.name}: window_samples must exceed 2n + 1 = {2 * n + 1}")
        self.corrections = 0
        self.confirmed = False
        self.gave_up = False
        self._v: list[float] = []
        self._mu: list[float] = []
        self._window_start = 0          # index of the first sample of the open window
        self._candidate: tuple[np.ndarray, float] | None = None   # (theta, SE) awaiting the check
        self._candidate_window: tuple[np.ndarray, np.ndarray] | None = None   # the window its SE is of
        self._last_estimate: np.ndarray | None = None
        self._pending: tuple[np.ndarray, np.ndarray] | None = None   # window of a correction in progress

    @property
    def samples(self) -> int:
        return len(self._v)

    def data(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self._v), np.asarray(self._mu)

    def add_sample(self, sample: Sample) -> list[IdentificationEvent]:
        if self.confirmed or self.gave_up:
            return []
        if not (math.isfinite(sample.creep_speed_kmh) and math.isfinite(sample.mu_hat)):
            return []   # a sample that cannot be fitted never reaches the estimator
        self._v.append(sample.creep_speed_kmh)
        self._mu.append(sample.mu_hat)
        self.on_sample(sample.creep_speed_kmh, sample.mu_hat)
        if self._candidate_window is not None and len(self._v) - self._window_start == 2:
            self._candidate_standard_error()       # on the next window's 2nd sample (the 1st settles the filter)
        events = []
        if self._pending is not None and (self.correction_ready()
                                          or len(self._v) - self._window_start >= self.window_samples):
            # a correction whose work was spread over the samples since its window closed
            v, mu = self._pending
            self._pending = None
            events = self._finish_correction(sample, self.correct_pending(), v, mu)
        if len(self._v) - self._window_start < self.window_samples:
            return events
        v = np.asarray(self._v[self._window_start:])
        mu = np.asarray(self._mu[self._window_start:])
        self._window_start = len(self._v)
        return events + self._on_window(sample, v, mu)

    def _on_window(self, sample: Sample, v: np.ndarray, mu: np.ndarray) -> list[IdentificationEvent]:
        if self._candidate is not None:
            if self._candidate_window is not None:
                self._candidate_standard_error()
            theta, se = self._candidate
            self._candidate = None
            if self._inside_band(v, mu, theta, se):
                self.confirmed = True
                self.theta = self.published_curve(theta)
                return [self._event(sample, "confirmed", math.nan)]
            # the window did not fit: it feeds the next correction instead
        estimate = self.correct(v, mu)
        if estimate is None:            # spread over the next samples (correction_ready / correct_pending)
            self._pending = (v, mu)
            return []
        return self._finish_correction(sample, estimate, v, mu)

    def _finish_correction(self, sample: Sample, estimate, v, mu) -> list[IdentificationEvent]:
        s = self.settings
        if not math.isfinite(float(np.sum(estimate))):     # NaN/inf propagate into the sum (one cheap check)
            estimate = self._last_estimate if self._last_estimate is not None else self.theta
        self.theta = self.estimate_to_theta(estimate)
        score = math.inf if self._last_estimate is None else j_ef(estimate, self._last_estimate)
        self._last_estimate = np.asarray(estimate, float)
        events = [self._event(sample, "correction", score)]
        self.corrections += 1
        if score <= self.k_pe:
            # the candidate's SE (eq. 29, on this window) is needed only when the next window closes:
            # it is computed on a later sample, not on this one (``_candidate_standard_error``)
            self._candidate = (self.theta.copy(), math.nan)
            self._candidate_window = (v, mu)
        elif self.corrections >= s.max_corrections:
            self.gave_up = True
        return events

    def _candidate_standard_error(self) -> None:
        v, mu = self._candidate_window
        self._candidate_window = None
        theta = self._candidate[0]
        self._candidate = (theta, self._standard_error(v, mu, theta))

    def _event(self, sample: Sample, kind: str, score: float) -> IdentificationEvent:
        mu_ci, creep_ci = self.peak_intervals(REPORT_LEVEL)
        return IdentificationEvent(sample.step, sample.t_s, kind, self.corrections,
                                   tuple(np.asarray(self.theta, float).tolist()), float(score), len(self._v),
                                   mu_ci, creep_ci)

    def peak_intervals(self, level: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """Intervals at ``level`` for the current curve's peak mu and peak creep (km/h); NaN where a
        strategy cannot say (the particle strategies: from their cloud; NLLS: from the fit)."""
        return NAN_INTERVAL, NAN_INTERVAL

    # the multi-level evaluation's SE (eq. 29) and band (eq. 28-31); observer-aware strategies override
    def _standard_error(self, v, mu, theta) -> float:
        return standard_error(v, mu, theta)

    def _inside_band(self, v, mu, theta, se) -> bool:
        return inside_confidence_band(v, mu, theta, se, self.c_lw, self.c_up)

    # -- what a strategy defines --------------------------------------------------------------
    def on_sample(self, creep_speed_kmh: float, mu_hat: float) -> None:
        """Called with every finite sample before the window bookkeeping (a filter steps here, so its
        cost is spread over the samples instead of landing on the window's last one)."""

    @abstractmethod
    def correct(self, window_v: np.ndarray, window_mu: np.ndarray) -> np.ndarray | None:
        """One correction from the newest window; returns the vector J_EF compares between corrections,
        or None when the work is spread over the next samples (then ``correction_ready`` says, after
        each later sample's ``on_sample``, when ``correct_pending`` can return it; the window
        bookkeeping goes on meanwhile, and the correction's event carries the sample it finished on)."""

    def published_curve(self, candidate: np.ndarray) -> np.ndarray:
        """The curve the confirmation reports: the candidate the confidence check accepted (the paper)."""
        return candidate

    def correction_ready(self) -> bool:
        return True

    def correct_pending(self) -> np.ndarray:
        raise NotImplementedError

    def estimate_to_theta(self, estimate: np.ndarray) -> np.ndarray:
        """Curve parameters from what ``correct`` returned (identity for strategies that fit theta)."""
        return np.asarray(estimate, float)
