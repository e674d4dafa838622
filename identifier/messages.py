"""What crosses the TCU's boundary: exactly what the CAN frames carry, as plain data.

The identifier consumes ``SensorReading`` and ``DriverDemand`` and produces ``TorqueCommand``, ``TcuStatus`` and
``IdentificationEvent``; a bus layer (``hil/``) maps these to and from frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

NAN_INTERVAL = (math.nan, math.nan)

# TCU identification stages as carried in the status frame
STAGE_MONITORING, STAGE_IDENTIFYING, STAGE_CONFIRMED, STAGE_GAVE_UP = 0, 1, 2, 3
STAGE_NAMES = {STAGE_MONITORING: "monitoring", STAGE_IDENTIFYING: "identifying",
               STAGE_CONFIRMED: "confirmed", STAGE_GAVE_UP: "gave_up"}


@dataclass(frozen=True)
class SensorReading:
    step: int
    motor_speed_rad_s: float
    train_speed_ms: float


@dataclass(frozen=True)
class DriverDemand:
    step: int            # the sensor step it goes with (sent right before that PlantSensor)
    torque_nm: float     # the driver's traction demand as motor torque


@dataclass(frozen=True)
class TorqueCommand:
    step: int            # echoes the sensor step it answers
    torque_nm: float


@dataclass(frozen=True)
class ObserverSample:
    step: int
    t_s: float
    creep_speed_kmh: float     # from measured speeds
    mu_hat: float              # eq. 5 from the observer's load torque
    load_torque_nm: float


#: the TCU keeps (and sends in a TcuEstimate frame) one peak estimate in this many periods: the run summary's
#: ``peak_estimate`` per rail change is computed from them (identifier/peak_estimate.py)
ESTIMATE_TRACE_STEPS = 10


@dataclass(frozen=True)
class IdentificationEvent:
    step: int
    t_s: float
    kind: str                  # "correction", "confirmed" or "unconfirmed" (gave up: best estimate)
    correction: int            # Q (the preliminary fit is 0)
    params: tuple[float, ...]  # lambda0, lambda1..n, tau1..n
    j_ef: float
    samples: int               # samples used so far
    peak_mu_ci: tuple[float, float] = NAN_INTERVAL        # 90 % interval of the curve's peak mu (NaN: none)
    peak_creep_ci: tuple[float, float] = NAN_INTERVAL     # 90 % interval of its peak creep, km/h
    # open: the peak may lie past the creeps seen, so both intervals' upper ends are the strategy's working
    # range, not the data (an open interval never counts as covering the truth)
    peak_open: bool = False
    # what the result is about: the time span (s) of the samples it rests on, first to last (NaN: not stated; a
    # strategy that forgets samples at a change of rail states the span since); a bench judges the result against
    # the rail under the wheel over that span (hil/benchmarks/control.py ``confirmation_figures``)
    samples_from_s: float = math.nan
    samples_to_s: float = math.nan


@dataclass(frozen=True)
class TcuStatus:
    step: int
    stage: int
    correction: int


@dataclass
class TcuOutput:
    command: TorqueCommand
    status: TcuStatus
    observer: ObserverSample | None = None
    events: list[IdentificationEvent] = field(default_factory=list)
    estimate: object | None = None     # the current rail's peak estimate (identifier/peak_estimate.py PeakEstimate)
