"""The measured side of a real run, read WITHOUT the truth.

``read_real_log`` is the only way the diagnosis reads a log.  It keeps what a real rig would have
recorded (sensor frames, torque commands, the TCU's observer output and identification events, the
exchange period) and drops everything else: the reality truth key, the plant's true states, the
scenario text (a ``[reality]`` table in it would leak the answer) and the run summary (its stage
times come from the plant's true states).

REAL_LOG is an MCAP file written by ``hil run`` or a python-can CAN log from a rig (``.log`` candump,
``.asc``, ``.blf``, ...: ``hil.gap.canlog``), whose frames carry the same readings (PlantSensor,
TorqueCommand, TcuStatus with the observer output, TcuResult) and no truth at all.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..log.read import LogError, read_log
from ..effects import TRUTH_KEY

from .canlog import CAN_LOG_SUFFIXES, read_can_log

TOPICS = {"/plant/sensor", "/tcu/command", "/tcu/observer", "/tcu/identification"}
KEPT_METADATA = ("run",)


@dataclass
class RealData:
    path: str
    period_s: float
    step: np.ndarray                 # exchange steps k (consecutive)
    t_s: np.ndarray
    motor_speed_rad_s: np.ndarray    # measured (plant side, /plant/sensor)
    train_speed_ms: np.ndarray
    torque_cmd_nm: np.ndarray        # /tcu/command, applied over [t_k, t_k+1)
    tcu_creep_kmh: np.ndarray        # what the TCU computed (/tcu/observer), NaN where missing
    tcu_mu_hat: np.ndarray
    identification: list = field(default_factory=list)   # dicts of /tcu/identification events
    metadata: dict = field(default_factory=dict)          # only KEPT_METADATA
    strategy: str = ""
    source: dict = field(default_factory=dict)            # format, frames read / skipped (CAN logs)

    @property
    def n(self) -> int:
        return len(self.step)


def read_real_log(path, period_s: float | None = None) -> RealData:
    """The measured side of the log at ``path``: an MCAP log of ``hil run``, or a python-can CAN log
    (suffix in ``canlog.CAN_LOG_SUFFIXES``) decoded through hil/hil.dbc, which needs ``period_s`` (the
    exchange period of the ``--model`` scenario: a CAN log does not record it)."""
    p = Path(path)
    if p.suffix.lower() in CAN_LOG_SUFFIXES:
        if period_s is None:
            raise LogError(f"{path}: a CAN log does not record the exchange period; give the model scenario")
        sensor, command, observer, events, source = read_can_log(p, period_s)
        # no strategy travels on the bus: the identification replays use the diagnosis' default
        return assemble(str(path), period_s, sensor, command, observer, events, {}, "", source)
    log = read_log(p, topics=TOPICS)
    log.metadata.pop(TRUTH_KEY, None)
    meta = {k: v for k, v in log.metadata.items() if k in KEPT_METADATA}
    log.metadata.clear()
    sensor = log.topic("/plant/sensor")
    if len(sensor) < 50:
        raise LogError(f"{path}: /plant/sensor has {len(sensor)} messages; hil gap needs at least 50")
    run = meta.get("run", {})
    try:
        period = float(run["exchange_period_s"])
    except (KeyError, ValueError):    # no (readable) period in the log's metadata: from its first two steps
        steps = np.array([m.step for m in sensor[:2]])
        ts = np.array([m.t_s for m in sensor[:2]])
        period = float((ts[1] - ts[0]) / max(steps[1] - steps[0], 1))
    events = [{"t_s": e.t_s, "kind": e.kind, "correction": e.correction, "params": list(e.params),
               "samples": e.samples} for e in log.topic("/tcu/identification")]
    strategy = next((e.strategy for e in log.topic("/tcu/identification")), run.get("strategy", ""))
    return assemble(str(path), period,
                    {m.step: (m.motor_speed_rad_s, m.train_speed_ms) for m in sensor},
                    {m.step: m.torque_nm for m in log.topic("/tcu/command")},
                    {m.step: (m.creep_speed_kmh, m.mu_hat) for m in log.topic("/tcu/observer")},
                    events, meta, strategy, {"format": "mcap"})


def assemble(path: str, period: float, sensor: dict, command: dict, observer: dict, events: list, meta: dict,
             strategy: str, source: dict) -> RealData:
    """RealData from per-step readings: ``sensor`` {step: (motor rad/s, train m/s)} must cover its
    steps without a gap; ``command`` {step: torque N·m} (a missing step holds the previous command);
    ``observer`` {step: (creep km/h, mu^)} (NaN where missing)."""
    if len(sensor) < 50:
        raise LogError(f"{path}: {len(sensor)} sensor readings; hil gap needs at least 50")
    k0, k1 = min(sensor), max(sensor)
    n = k1 - k0 + 1
    if n != len(sensor):
        missing = next(k for k in range(k0, k1 + 1) if k not in sensor)
        raise LogError(f"{path}: sensor readings have gaps (missing steps, first {missing}); hil gap needs "
                       f"consecutive readings")
    nan = lambda: np.full(n, np.nan)  # noqa: E731
    motor, train, torque, creep, mu = nan(), nan(), nan(), nan(), nan()
    for k, (w, v) in sensor.items():
        motor[k - k0], train[k - k0] = w, v
    for k, te in command.items():
        if 0 <= k - k0 < n:
            torque[k - k0] = te
    for k, (c, m) in observer.items():
        if 0 <= k - k0 < n:
            creep[k - k0], mu[k - k0] = c, m
    if not (np.all(np.isfinite(motor)) and np.all(np.isfinite(train))):
        raise LogError(f"{path}: non-finite sensor readings")
    if np.isnan(torque).all():
        raise LogError(f"{path}: no torque commands: the model has no input to replay")
    # a missing command holds the previous one
    for i in range(n):
        if np.isnan(torque[i]):
            torque[i] = torque[i - 1] if i else torque[~np.isnan(torque)][0]
    steps = np.arange(k0, k0 + n)
    return RealData(str(path), period, steps, steps * period, motor, train, torque, creep, mu, events, meta,
                    strategy, source)


def describe(data: RealData) -> str:
    """A JSON dump of everything the diagnosis sees (tests check the truth is not in it)."""
    return json.dumps({"path": data.path, "metadata": data.metadata, "identification": data.identification,
                       "strategy": data.strategy})
