"""Reality on the wiring: CAN delay, jitter and loss of sensor frames, and the one place that
turns a scenario's ``[reality]`` table into a reality plant, sensor wrapper and bus wrapper.

The CAN effect sits between the plant's ``sense()`` and the TCU: frame j is sent at j*T and arrives
at j*T + delay + jitter*U(0,1) unless lost (probability ``loss``).  At its period k the TCU uses the
newest frame that has arrived by k*T (a TCU that samples its latest received value), re-stamped
with its own step k.  The realised mean delay is kept for the truth record.

The truth (effects and parameters) is written to the log under ONE metadata key, ``TRUTH_KEY``;
the gap diagnosis reads logs only through ``hil.gap.data.read_real_log``, which drops that key.
"""
from __future__ import annotations

import heapq
import json

import numpy as np

from identifier import SensorReading
from plant.reality import EFFECTS, RealityPlant, RealitySensors, effects_from_table, fill_defaults

TRUTH_KEY = "reality_truth"


class CanReality:
    """``deliver(reading) -> reading the TCU uses this period``; call once per period, in order."""

    def __init__(self, delay_ms: float, jitter_ms: float, loss: float, period_s: float, seed: int):
        self.delay_s = delay_ms * 1e-3
        self.jitter_s = jitter_ms * 1e-3
        self.loss = loss
        self.period_s = period_s
        self._rng = np.random.default_rng([seed, 0xCA4])
        self._queue: list[tuple[float, int, SensorReading]] = []   # (arrival time, send step, reading)
        self._newest: SensorReading | None = None
        self.delays_periods: list[int] = []   # realised (TCU step - send step) per period
        self.lost = 0

    def deliver(self, reading: SensorReading) -> SensorReading:
        k = reading.step
        t_now = k * self.period_s
        if self._newest is None:
            self._newest = reading               # the TCU starts with the initial value
        if self._rng.random() < self.loss:
            self.lost += 1
        else:
            arrival = t_now + self.delay_s + self.jitter_s * self._rng.random()
            heapq.heappush(self._queue, (arrival, k, reading))
        while self._queue and self._queue[0][0] <= t_now + 1e-9:
            _, j, r = heapq.heappop(self._queue)
            if r.step >= self._newest.step:
                self._newest = r
        self.delays_periods.append(k - self._newest.step)
        return SensorReading(k, self._newest.motor_speed_rad_s, self._newest.train_speed_ms)

    def realised(self) -> dict:
        d = np.asarray(self.delays_periods, float)
        return {"mean_delay_ms": float(d.mean() * self.period_s * 1e3) if d.size else 0.0,
                "lost_frames": self.lost, "frames": len(self.delays_periods)}


class Reality:
    """What a scenario's ``[reality]`` table asks for, ready to plug into the loop."""

    def __init__(self, scenario, seed: int):
        raw = scenario.extra.get("reality") or {}
        try:
            effects = effects_from_table(raw)
        except ValueError as e:
            from .scenario import ScenarioError
            raise ScenarioError(f"{scenario.path}: {e}") from None
        cfg = scenario.plant_config()
        self.effects = fill_defaults(effects, cfg)
        self.active = bool(self.effects)
        self.plant = RealityPlant(cfg, self.effects) \
            if any(EFFECTS[n].level == "plant" for n in self.effects) else None
        self.can = None
        if "can" in self.effects:
            c = self.effects["can"]
            self.can = CanReality(c["delay_ms"], c["jitter_ms"], c["loss"], scenario.run.exchange_period_s, seed)
        self._sensor_effects = {n: p for n, p in self.effects.items() if EFFECTS[n].level == "sensor"}
        self.period_s = scenario.run.exchange_period_s

    def wrap_sensors(self, sensors):
        return RealitySensors(sensors, self._sensor_effects, self.period_s) if self._sensor_effects else sensors

    def deliver(self, reading: SensorReading) -> SensorReading:
        return self.can.deliver(reading) if self.can else reading

    def truth(self) -> dict:
        out = {"effects": json.dumps(self.effects)}
        if self.can:
            out["can_realised"] = json.dumps(self.can.realised())
        return out

    def record_truth(self, recorder) -> None:
        """Write the truth under TRUTH_KEY (call at the end of the run: it holds realised figures)."""
        if recorder is not None and self.active:
            recorder.metadata(TRUTH_KEY, self.truth())


def with_reality(scenario, effects: dict):
    """The scenario with ``effects`` ({name: params}) merged into its ``[reality]`` table."""
    import dataclasses

    table = dict(scenario.extra.get("reality") or {})
    table.update({k: {p: v for p, v in params.items() if v is not None} for k, params in effects.items()})
    return dataclasses.replace(scenario, extra={**scenario.extra, "reality": table})
