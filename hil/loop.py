"""The fixed-step HIL loop: the plant side, the TCU side, and the in-process wiring of the two.

The plant side owns the true states, the sensors and the stage tracker and records them; the TCU
side owns the identifier and records what it computes.  Between them travels only what the CAN
frames carry (``SensorReading`` one way, ``TorqueCommand`` and results the other).
"""
from __future__ import annotations

import contextlib
import gc
import time
from pathlib import Path

from identifier import SensorReading, TorqueCommand, TractionIdentifier
from identifier.messages import STAGE_NAMES, TcuOutput
from plant import SensorModel, StageTracker, WheelsetPlant

from .progress import Progress
from .recording import Recorder, interrupts_between_writes, package_versions
from .summary import observer_lag_ms, summarise

#: how long after the fault the true mu is kept for measuring the observer lag
LAG_WINDOW_S = 0.3


@contextlib.contextmanager
def collector_paused(active: bool = True):
    """No garbage collection inside (when ``active``), as the real-time loops run: a full collection
    over scipy's and casadi's objects costs whole periods.  The objects alive on entry are frozen
    (never scanned again); on exit the collector is as it was."""
    if not active:
        yield
        return
    was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


def log_path(scenario, strategy: str, seed: int, out_dir=None) -> Path:
    return Path(out_dir or "logs") / f"{scenario.name}-{strategy}-{seed}.mcap"


class PlantSide:
    """Plant, sensors and stage tracking; ``sense()`` then ``apply(command)`` once per period."""

    def __init__(self, scenario, seed: int, recorder: Recorder | None, plant=None):
        """``plant``: anything with WheelsetPlant's interface (an FMU, a reality emulator); default CasADi."""
        self.scenario = scenario
        cfg = scenario.plant_config()
        self.plant = plant if plant is not None else WheelsetPlant(cfg)
        self.sensors = SensorModel(scenario.sensors, seed)
        self.tracker = StageTracker(cfg.fault_time_s, scenario.fault_curve.peak()[0])
        self.recorder = recorder
        self.truth_t: list[float] = []     # (t, mu) just after the fault, for the observer-lag figure
        self.truth_mu: list[float] = []

    @property
    def step(self) -> int:
        return self.plant.step_index

    def sense(self) -> SensorReading:
        s = self.plant.state
        stage = self.tracker.update(s.t_s, s.creep_speed_kmh)
        omega, v = self.sensors.measure(s.motor_speed_rad_s, s.train_speed_ms)
        k = self.plant.step_index
        if 0 <= s.t_s - self.scenario.run.fault_time_s <= LAG_WINDOW_S:
            self.truth_t.append(s.t_s)
            self.truth_mu.append(s.mu)
        if self.recorder:
            self.recorder.write("/plant/state", s.t_s, step=k, t_s=s.t_s, motor_speed_rad_s=s.motor_speed_rad_s,
                                train_speed_ms=s.train_speed_ms, creep_speed_kmh=s.creep_speed_kmh, mu=s.mu,
                                load_torque_nm=s.load_torque_nm, torque_nm=s.torque_nm,
                                fault_active=s.fault_active, stage=stage)
            self.recorder.write("/plant/sensor", s.t_s, step=k, t_s=s.t_s, motor_speed_rad_s=omega,
                                train_speed_ms=v)
        return SensorReading(k, omega, v)

    def apply(self, command: TorqueCommand) -> None:
        self.plant.step(command.torque_nm)


class TcuSide:
    """The identifier plus what it keeps for the summary (observer trace after the fault)."""

    def __init__(self, scenario, strategy: str, seed: int, recorder: Recorder | None):
        self.identifier = TractionIdentifier(scenario.identifier_settings(), strategy, seed)
        self.recorder = recorder
        self.events = []
        self.observer_t: list[float] = []
        self.observer_mu: list[float] = []
        self._fault_time_s = scenario.run.fault_time_s

    def on_sensor(self, reading: SensorReading) -> TcuOutput:
        out = self.identifier.on_sensor(reading)
        self.record(out)
        return out

    def record(self, out: TcuOutput) -> None:
        t_s = out.command.step * self.identifier.settings.period_s
        obs = out.observer
        if obs is not None and 0 <= obs.t_s - self._fault_time_s <= LAG_WINDOW_S:
            self.observer_t.append(obs.t_s)
            self.observer_mu.append(obs.mu_hat)
        self.events.extend(out.events)
        rec = self.recorder
        if not rec:
            return
        rec.write("/tcu/command", t_s, step=out.command.step, t_s=t_s, torque_nm=out.command.torque_nm)
        if obs is not None:
            rec.write("/tcu/observer", obs.t_s, step=obs.step, t_s=obs.t_s, creep_speed_kmh=obs.creep_speed_kmh,
                      mu_hat=obs.mu_hat, load_torque_nm=obs.load_torque_nm)
        st = out.status
        rec.write("/tcu/status", t_s, step=st.step, t_s=t_s, stage=st.stage, stage_name=STAGE_NAMES[st.stage],
                  correction=st.correction)
        for e in out.events:
            rec.write("/tcu/identification", e.t_s, step=e.step, t_s=e.t_s, kind=e.kind, correction=e.correction,
                      params=list(e.params), j_ef=e.j_ef, samples=e.samples, strategy=self.identifier.strategy_name)
            rec.event(e.t_s, "INFO", f"{e.kind} Q={e.correction} after {e.samples} samples: "
                      + ", ".join(f"{x:.5g}" for x in e.params))


def start_recording(scenario, strategy: str, seed: int, bus: str, mode: str, path) -> Recorder:
    rec = Recorder(path)
    # the TOML as written plus the --set overrides, so replay and view rebuild exactly this scenario
    rec.metadata("scenario", {"name": scenario.name, "path": scenario.path, "toml": scenario.source_text,
                              "overrides": scenario.overrides})   # Recorder.metadata JSON-encodes it
    rec.metadata("versions", package_versions())
    rec.metadata("run", {"strategy": strategy, "seed": str(seed), "bus": bus, "mode": mode,
                         "exchange_period_s": repr(scenario.run.exchange_period_s)})
    return rec


def finish_summary(scenario, strategy, seed, bus, plant_side: PlantSide, tcu_side: TcuSide, path, extra) -> dict:
    ident = tcu_side.identifier
    v, mu = ident.strategy.data()
    detected = ident.detector.detected_step
    lag = observer_lag_ms(plant_side.truth_t, plant_side.truth_mu, tcu_side.observer_mu,
                          scenario.run.fault_time_s, plant_side.tracker.serious_time_s or scenario.run.duration_s,
                          scenario.run.exchange_period_s) \
        if len(tcu_side.observer_mu) == len(plant_side.truth_mu) else None
    extra = {"observer_lag_ms": lag, **extra}
    return summarise(scenario=scenario, strategy=strategy, seed=seed, bus=bus, tracker=plant_side.tracker,
                     events=tcu_side.events, samples_v=v, samples_mu=mu,
                     t_detected_s=None if detected is None else detected * scenario.run.exchange_period_s,
                     mcap_path=path, extra=extra)


def run_inprocess(scenario, strategy: str = "nlls", seed: int | None = None, out_dir=None, record: bool = True,
                  progress: bool | None = None, plant=None) -> dict:
    """Plant and identifier in one process, no bus: the reference loop every bus must reproduce.

    ``plant``: a plant object (e.g. ``plant.fmu_plant.FmuPlant``, see hil/plant_factory.py) instead of
    the CasADi model; the caller closes it."""
    seed = scenario.run.seed if seed is None else seed
    path = log_path(scenario, strategy, seed, out_dir) if record else None
    rec = start_recording(scenario, strategy, seed, "inprocess", "lockstep", path) if record else None
    from .reality_bus import Reality   # [reality] table / --reality: a "real" run (issue 7)
    reality = Reality(scenario, seed)
    if rec and hasattr(plant, "metadata"):
        rec.metadata("plant", plant.metadata())
    plant_side = PlantSide(scenario, seed, rec, plant=plant if plant is not None else reality.plant)
    plant_side.sensors = reality.wrap_sensors(plant_side.sensors)
    tcu_side = TcuSide(scenario, strategy, seed, rec)
    with interrupts_between_writes():   # Ctrl-C / SIGTERM close the log properly, never mid-write
        bar = Progress(scenario.steps, f"{scenario.name} {strategy}", progress)
        wall0 = time.perf_counter()
        summary = None
        try:
            for _ in range(scenario.steps):
                reading = reality.deliver(plant_side.sense())
                out = tcu_side.on_sensor(reading)
                plant_side.apply(out.command)
                if plant_side.step % 1000 == 0:
                    bar.update(plant_side.step)
            wall = time.perf_counter() - wall0
            summary = finish_summary(scenario, strategy, seed, "inprocess", plant_side, tcu_side, path,
                                     {"mode": "lockstep", "wall_s": wall, "sim_s": plant_side.plant.t_s,
                                      "messages": rec.messages + 1 if rec else 0})  # + the summary
        finally:
            bar.close()
            if rec:
                with rec.atomic():
                    if summary is None:
                        rec.event(plant_side.plant.t_s, "ERROR", "run aborted")
                    reality.record_truth(rec)
                    rec.close(summary)
    return summary
