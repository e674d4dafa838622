"""The traction control unit's identifier, at frame level: sensor readings in, commands and
identification results out.  The same object runs in the TCU process, in replay and in benchmarks.

Pipeline per reading: observer -> mu^ and creep speed -> slip detector -> the control law's torque
(identifier/control: the driver's demand, or a closed-loop law acting on what was learnt) -> (after the
observer settles) samples to the strategy.  A closed-loop law may re-arm the identifier (a fresh
detector and strategy) once the demand passes through again, so each new drop is identified afresh;
the strategy is told the loop is closed (``Strategy.closed_loop``: the rail may change under a slip's
samples, and ``gp`` then dates the change).  An observer-aware strategy (``Strategy.observer_aware``) gets
every sample from the detected slip start on instead, each with the creep of the same instant and
the observer's speed innovation (it models the observer's transient rather than waiting it out).
"""
from __future__ import annotations

import math
from collections import deque

from . import curve as curve_model
from .control import DEFAULT_LAW, ControlInput, make_controller
from .drill import Drill
from .excitation import Excitation
from .messages import (ESTIMATE_TRACE_STEPS, STAGE_CONFIRMED, STAGE_GAVE_UP, STAGE_IDENTIFYING, STAGE_MONITORING,
                       ObserverSample, SensorReading, TcuOutput, TcuStatus, TorqueCommand)
from .observer import LoadTorqueObserver
from .peak_estimate import PeakEstimator
from .settings import IdentifierSettings
from .strategies import DEFAULT_STRATEGY, Sample, make_strategy

KMH_PER_MS = 3.6


def creep_speed_kmh(reading: SensorReading, vehicle) -> float:
    """The creep speed from a reading: wheel rim speed (motor speed / gear ratio x radius) minus the
    train speed, in km/h."""
    return KMH_PER_MS * (reading.motor_speed_rad_s / vehicle.gear_ratio * vehicle.wheel_radius_m
                         - reading.train_speed_ms)


class SlipDetector:
    """Flags a slipping fault when the creep speed stays above its pre-fault mean by more than
    ``max(threshold_kmh, sigmas * std)`` for ``consecutive`` readings.

    Mean and standard deviation come from the last ``baseline_samples`` readings before the
    detection, so a slow drift of the operating point does not trigger it, and the noise-scaled
    threshold keeps false alarms negligible over long runs (a single 4-sigma outlier is not a slip).
    A reading more than ``hold_sigmas`` std above the mean does not join the baseline: otherwise a
    slip whose creep rises gently lifts its own baseline's mean and std as fast as it rises and is
    never detected.
    """

    def __init__(self, threshold_kmh: float, baseline_samples: int, sigmas: float = 6.0, consecutive: int = 2,
                 hold_sigmas: float = 3.0):
        self.threshold_kmh = threshold_kmh
        self.sigmas = sigmas
        self.hold_sigmas = hold_sigmas
        self.consecutive = consecutive
        self._history: deque[float] = deque(maxlen=baseline_samples)
        # the baseline's running sum and sum of squares (Python floats: a numpy mean and std of 50
        # numbers each reading were most of the TCU's work while monitoring), summed afresh
        # each time the window has turned over, so rounding cannot drift over a long run
        self._sum = self._sum_sq = 0.0
        self._until_resum = baseline_samples
        self._above = 0
        self.detected_step: int | None = None

    def update(self, step: int, creep_speed_kmh: float) -> bool:
        if self.detected_step is not None:
            return True
        h = self._history
        n = len(h)
        if n == h.maxlen:
            mean = self._sum / n
            std = math.sqrt(max(self._sum_sq / n - mean * mean, 0.0))
            rise = creep_speed_kmh - mean
            if rise > max(self.threshold_kmh, self.sigmas * std):
                self._above += 1
                if self._above >= self.consecutive:
                    self.detected_step = step - self.consecutive + 1   # the slip began at the first one
                    return True
                return False        # a candidate is not part of the baseline
            self._above = 0
            if rise > self.hold_sigmas * std:
                return False        # held out of the baseline (class docstring)
            oldest = h[0]
            self._sum -= oldest
            self._sum_sq -= oldest * oldest
        h.append(creep_speed_kmh)
        self._sum += creep_speed_kmh
        self._sum_sq += creep_speed_kmh * creep_speed_kmh
        self._until_resum -= 1
        if self._until_resum <= 0:
            self._until_resum = h.maxlen
            self._sum = math.fsum(h)
            self._sum_sq = math.fsum(x * x for x in h)
        return False


class TractionIdentifier:
    """``on_sensor(reading) -> TcuOutput`` (or its two halves, ``command(reading)`` then ``work(command)``);
    holds the observer, the detector and one strategy."""

    def __init__(self, settings: IdentifierSettings, strategy: str = DEFAULT_STRATEGY, seed: int = 0,
                 control: str = DEFAULT_LAW, control_options: dict | None = None):
        self.settings = settings
        self.strategy_name = strategy
        self.strategy = make_strategy(strategy, settings, seed)
        self.seed = seed
        #: the driver's demand (motor torque): the scenario's until a DriverDemand frame says otherwise
        self.demand_nm = settings.torque_demand_nm
        nominal_peak_creep_kmh = curve_model.peak(settings.initial_guess)[0]
        self.control = control
        self.controller = make_controller(control, settings.vehicle, nominal_peak_creep_kmh, control_options)
        self._open_loop = control == DEFAULT_LAW
        self.strategy.closed_loop = not self._open_loop
        self.latest_event = None      # the strategy's last identification event (since the last re-arm)
        self._peak_of = (None, math.nan)   # (event, its curve's peak creep)
        self.rearms = 0
        self.excitation = Excitation.from_dict(settings.excitation)
        v = settings.vehicle
        self.observer = LoadTorqueObserver(v.equivalent_inertia_kgm2, settings.period_s,
                                           settings.observer_pole_rad_s)
        self.detector = SlipDetector(settings.detection_creep_rise_kmh, settings.baseline_samples)
        lag_steps = round(self.observer.lag_s / settings.period_s) if settings.lag_compensation else 0
        self._creep_history: deque[float] = deque(maxlen=lag_steps + 1)
        self._settle_steps = round(settings.settle_time_s / settings.period_s)
        self._observer_aware = bool(getattr(self.strategy, "observer_aware", False))
        self._wants_readings = bool(getattr(self.strategy, "wants_readings", False))
        # the readings between the slip's first step and its detection (consecutive - 1 of them)
        self._recent: deque[Sample] = deque(maxlen=self.detector.consecutive + 1)
        self.rejected_readings = 0
        self._pending = None          # what ``command`` leaves for ``work``
        self._last_torque = settings.torque_demand_nm
        # a small copy of the strategy identifying a synthetic slip while there is no real one, so the
        # strategy's code is warm when the fault comes (identifier/drill.py); not for strategies
        # whose samples are not all cheap (``Strategy.keeps_warm``), nor for those that model the
        # observer's output (the drill has speed readings or (creep, mu) samples, not an observer)
        # the predictive estimate of the current rail's peak (identifier/peak_estimate.py), every period once the
        # observer has settled from its start; ``estimates`` keeps every one when a benchmark asks for them
        self.estimator = PeakEstimator(settings.period_s, settings.options.get("peak_estimate"))
        self.estimate = None
        self.estimates: list | None = None
        #: every ``ESTIMATE_TRACE_STEPS``-th estimate, always (the run summary's ``peak_estimate`` per rail change)
        self.estimate_trace: list = []
        self.events_log: list | None = None    # every identification event, when a benchmark asks for them
        self.drill = (Drill(settings, strategy, settings.drill_particles, seed)
                      if settings.drill_particles > 0 and self.strategy.keeps_warm
                      and (self._wants_readings or not self._observer_aware) else None)

    def stage(self) -> int:
        if self.strategy.confirmed:
            return STAGE_CONFIRMED
        if self.strategy.gave_up:
            return STAGE_GAVE_UP
        return STAGE_IDENTIFYING if self.detector.detected_step is not None else STAGE_MONITORING

    def command_nm(self, step: int) -> float:
        """The open-loop torque after the reading of ``step``: the demand, with the excitation once a
        slip has been detected (identifier/excitation.py: a function of the step and seed only)."""
        s = self.settings
        return self.excitation.command_nm(self.demand_nm, step, self.detector.detected_step, s.period_s, self.seed)

    def control_input(self, step: int, creep: float, load_torque: float, mu_hat: float) -> ControlInput:
        """What the control law sees now: the reading, the observer, the demand and the latest curve."""
        e = self.latest_event
        ci = None
        peak_creep = math.nan
        confirmed = False
        if e is not None:
            if all(math.isfinite(x) for x in e.peak_creep_ci):
                # an open interval's upper end is the strategy's range, not the data's: no ceiling
                ci = (e.peak_creep_ci[0], math.inf if getattr(e, "peak_open", False) else e.peak_creep_ci[1])
            confirmed = e.kind in ("confirmed", "unconfirmed")
            if confirmed and len(e.params) >= 3:
                if self._peak_of[0] is not e:        # once per event: a grid search costs tens of us
                    self._peak_of = (e, curve_model.peak(e.params)[0])
                peak_creep = self._peak_of[1]
        s = self.settings
        return ControlInput(step, step * s.period_s, s.period_s, self.demand_nm, creep, load_torque, mu_hat,
                            self.detector.detected_step is not None, ci,
                            tuple(e.peak_mu_ci) if e is not None else None, confirmed, peak_creep, self.estimate)

    def use_controller(self, controller) -> None:
        """Act through ``controller`` (anything with ``torque_nm(ControlInput)`` and ``wants_rearm``) instead
        of the law named at construction: the benchmark's oracle and prior laws, never a run's."""
        self.controller = controller
        self._open_loop = False
        self.strategy.closed_loop = True

    def rearm(self) -> None:
        """A fresh detector and strategy (the observer runs on): the next drop is identified afresh."""
        s = self.settings
        self.detector = SlipDetector(s.detection_creep_rise_kmh, s.baseline_samples)
        self.strategy = make_strategy(self.strategy_name, s, self.seed + self.rearms + 1)
        self.strategy.closed_loop = not self._open_loop
        self._recent.clear()
        self.latest_event = None
        self.rearms += 1

    def on_sensor(self, reading: SensorReading) -> TcuOutput:
        """The whole answer to one reading: ``command`` then ``work``."""
        return self.work(self.command(reading))

    def command(self, reading: SensorReading) -> TorqueCommand:
        """The torque command answering ``reading``: observer -> creep speed -> slip detector ->
        command (no fitting: cheap).  The rest of the reading's work (the drill, the
        strategy) waits for ``work``, so a TCU can send the command first: the plant waits for it,
        and nothing else does (a real TCU's control task answers before its background work)."""
        if not (math.isfinite(reading.motor_speed_rad_s) and math.isfinite(reading.train_speed_ms)):
            # a reading that cannot be trusted: the planned command, nothing fed downstream
            self.rejected_readings += 1
            self._pending = None
            return TorqueCommand(reading.step, self.command_nm(reading.step) if self._open_loop else self._last_torque)
        v = self.settings.vehicle
        t_s = reading.step * self.settings.period_s
        innovation = reading.motor_speed_rad_s - self.observer.speed_rad_s   # y(k) - omega^(k), before the update
        load_torque = self.observer.update(reading.motor_speed_rad_s, self._last_torque)
        mu_hat = load_torque / v.torque_per_mu_nm
        creep = creep_speed_kmh(reading, v)
        self._creep_history.append(creep)
        paired_creep = self._creep_history[0]   # v_s(k - lag): the creep mu^(k) really belongs to
        observer = ObserverSample(reading.step, t_s, creep, mu_hat, load_torque)
        detected_before = self.detector.detected_step is not None
        slipping = self.detector.update(reading.step, creep)
        if self._open_loop:
            torque = self.command_nm(reading.step)       # what is applied from this reading to the next
        else:
            torque = self.controller.torque_nm(self.control_input(reading.step, creep, load_torque, mu_hat))
            if self.controller.wants_rearm:
                self.rearm()
                slipping = False
        self._last_torque = torque
        self._pending = (reading, observer, innovation, paired_creep, slipping, detected_before)
        return TorqueCommand(reading.step, torque)

    def work(self, command: TorqueCommand) -> TcuOutput:
        """The rest of the answer to the reading ``command`` answered: the drill while monitoring,
        the strategy's sample once slipping; the output carries ``command`` and the events."""
        pending, self._pending = self._pending, None
        if pending is None:
            return TcuOutput(command, self._status(command.step))
        reading, observer, innovation, paired_creep, slipping, detected_before = pending
        t_s = observer.t_s
        events = []
        if reading.step >= self._settle_steps and not self._open_loop:
            # the estimate is for a control law: an open-loop run (the paper's, the default) does not pay
            # its cost (docs/design/control.md: p99 350 us a sample with it, 159 us without, at load 10)
            self.estimate = self.estimator.add(reading.step, t_s, paired_creep, observer.mu_hat)
            if self.estimates is not None:
                self.estimates.append(self.estimate)
            if reading.step % ESTIMATE_TRACE_STEPS == 0:
                self.estimate_trace.append(self.estimate)
        if self.drill is not None and (self.detector.detected_step is None or (
                not self._observer_aware and reading.step - self.detector.detected_step < self._settle_steps - 1)):
            self.drill.tick()       # monitoring, or settling: the strategy's first sample is still ahead
        self.strategy.rail_estimate = self.estimate     # gp's test of a confirmation's window (closed loop)
        if self._wants_readings:
            self.strategy.on_reading(reading.step, reading.motor_speed_rad_s, reading.train_speed_ms)
        if self._observer_aware:
            sample = Sample(reading.step, t_s, observer.creep_speed_kmh, observer.mu_hat, innovation,
                            reading.motor_speed_rad_s, reading.train_speed_ms, command.torque_nm)
            if slipping:
                if not detected_before:     # just detected: the buffered readings since the slip's start first
                    for s in self._recent:
                        if s.step >= self.detector.detected_step:
                            events.extend(self.strategy.add_sample(s))
                events.extend(self.strategy.add_sample(sample))
            else:
                self._recent.append(sample)
        elif slipping:
            if reading.step - self.detector.detected_step >= self._settle_steps:
                events = self.strategy.add_sample(Sample(reading.step, t_s, paired_creep, observer.mu_hat))
        if events:
            self.latest_event = events[-1]
            if self.events_log is not None:
                self.events_log.extend(events)
        return TcuOutput(command, self._status(reading.step), observer, events, self.estimate)

    def _status(self, step: int) -> TcuStatus:
        return TcuStatus(step, self.stage(), self.strategy.corrections)
