"""The measured side of a real run, read WITHOUT the truth.

``read_real_log`` is the only way the diagnosis reads a log.  It keeps what a real rig would have
recorded (sensor frames, torque commands, the TCU's observer output and identification events, the
exchange period) and drops everything else: the reality truth key, the plant's true states, the
scenario text (a ``[reality]`` table in it would leak the answer) and the run summary (its stage
times come from the plant's true states).

REAL_LOG is an MCAP file written by ``hil run``.  A python-can log from a rig (``.asc``/``.blf``/
``.log``) is not read yet: it would need the DBC decoding of the frame layer (hil/frames.py) and
carries no observer topic; ``read_real_log`` says so in one line.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..logread import LogError, read_log
from ..effects import TRUTH_KEY

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

    @property
    def n(self) -> int:
        return len(self.step)


def read_real_log(path) -> RealData:
    p = Path(path)
    if p.suffix.lower() in (".asc", ".blf", ".log", ".trc", ".csv"):
        raise LogError(f"{path}: python-can CAN logs are not read by hil gap yet (MCAP logs from hil run are)")
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
    except (KeyError, ValueError):
        steps = np.array([m.step for m in sensor[:2]])
        ts = np.array([m.t_s for m in sensor[:2]])
        period = float((ts[1] - ts[0]) / max(steps[1] - steps[0], 1))
    k0 = sensor[0].step
    n = sensor[-1].step - k0 + 1
    nan = lambda: np.full(n, np.nan)  # noqa: E731
    motor, train, torque, creep, mu = nan(), nan(), nan(), nan(), nan()
    for m in sensor:
        motor[m.step - k0] = m.motor_speed_rad_s
        train[m.step - k0] = m.train_speed_ms
    for m in log.topic("/tcu/command"):
        if 0 <= m.step - k0 < n:
            torque[m.step - k0] = m.torque_nm
    for m in log.topic("/tcu/observer"):
        if 0 <= m.step - k0 < n:
            creep[m.step - k0] = m.creep_speed_kmh
            mu[m.step - k0] = m.mu_hat
    if np.isnan(motor).any() or np.isnan(train).any():
        raise LogError(f"{path}: /plant/sensor has gaps (missing steps); hil gap needs consecutive readings")
    if np.isnan(torque).all():
        raise LogError(f"{path}: no /tcu/command messages: the model has no input to replay")
    # a missing command holds the previous one
    for i in range(n):
        if np.isnan(torque[i]):
            torque[i] = torque[i - 1] if i else torque[~np.isnan(torque)][0]
    events = [{"t_s": e.t_s, "kind": e.kind, "correction": e.correction, "params": list(e.params),
               "samples": e.samples} for e in log.topic("/tcu/identification")]
    strategy = next((e.strategy for e in log.topic("/tcu/identification")), run.get("strategy", ""))
    steps = np.arange(k0, k0 + n)
    return RealData(str(path), period, steps, steps * period, motor, train, torque, creep, mu, events, meta,
                    strategy)


def describe(data: RealData) -> str:
    """A JSON dump of everything the diagnosis sees (tests check the truth is not in it)."""
    return json.dumps({"path": data.path, "metadata": data.metadata, "identification": data.identification,
                       "strategy": data.strategy})
