"""The identification outcome the gap moves: the TCU's identifier on the real run (from the log's
events) against the same identifier run offline on the nominal model's and the augmented model's
speeds (``replay``), so the report says how the gap moves the identified friction curve.

A replay measures the model's plant trajectory through the scenario's sensor model (noise, quantum),
then through the named candidate's sensor side (delay, quanta, CAN frame map), and feeds the readings
to a fresh ``TractionIdentifier`` period by period.  Identification is sensitive to the noise draw,
so each replay runs once per seed in ``REPLAY_SEEDS`` and reports the median and the range.
Outcome per run: identified, T_det (first serious-stage sample after the fault, ``where.stages``),
RT = ``identifier.metrics.rt_percent``, the identified curve's peak and its errors against the
scenario's fault curve (``identifier.metrics.peak_errors``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from identifier import SensorReading, TractionIdentifier
from identifier.metrics import peak_errors, rt_percent
from plant import SensorModel

from .candidates import Context, Fit
from .model import Simulator, shift
from .where import stages

REPLAY_SEEDS = (424242, 424243, 424244, 424245, 424246)   # sensor-noise draws of the identification replays


def outcome(ctx: Context, events, creep) -> dict:
    """What an identification run came to (identified, T_det from ``creep``, RT, curve, peak errors)."""
    d, sc = ctx.data, ctx.scenario
    t_f = sc.run.fault_time_s
    st = stages(d.t_s, creep, t_f, sc.fault_curve.peak()[0])
    idx = np.flatnonzero(st == 2)
    tdet = float(d.t_s[idx[0]] - t_f) if idx.size else math.nan
    conf = next((e for e in events if e["kind"] == "confirmed"), None)
    last = conf or (events[-1] if events else None)
    out = {"identified": conf is not None, "t_det_s": tdet,
           "t_identified_s": conf["t_s"] if conf else None,
           "rt_percent": rt_percent(conf["t_s"] if conf else None, t_f, tdet),
           "params": last["params"] if last else None,
           # the same keys whether or not the run published a curve (None: no curve to judge)
           "peak_mu_err_percent": None, "peak_creep_err_percent": None, "peak_mu": None, "peak_creep_kmh": None}
    if last:
        out.update(peak_errors(np.asarray(last["params"]), sc.fault_curve))
    return out


def identification(ctx: Context, nominal, best: Fit | None, creep_meas) -> dict:
    d = ctx.data
    strategy = d.strategy or "nlls"
    real = {"source": "real run (log)", **outcome(ctx, d.identification, creep_meas)}
    nom = replay(ctx, nominal.extra["plant_motor"], nominal.extra["plant_train"], {}, strategy,
                      "nominal model replay")
    out = {"strategy": strategy, "real": real, "nominal_replay": nom}
    if best is not None:
        x0 = np.array(best.extra["x0"])
        if "plant" in best.extra:
            name, params = best.extra["plant"]
            motor, train = Simulator(ctx.cfg, name, (), params, d.n).run([], x0, d.torque_cmd_nm)
        else:
            motor, train = ctx.simulator(None, (), {}).run([], x0, d.torque_cmd_nm)
        out["augmented_replay"] = replay(ctx, motor, train, best.extra, strategy,
                                              f"nominal + {best.name} replay")
    # how the gap moves the identified curve
    moves = {}
    for key in ("peak_mu", "peak_creep_kmh"):
        if real.get(key) is not None and nom.get(key) is not None:
            # a replay may identify a degenerate curve (peak 0): no relative move then
            moves[f"real_vs_nominal_{key}_percent"] = ((real[key] - nom[key]) / abs(nom[key]) * 100
                                                       if nom[key] != 0 else None)
        aug = out.get("augmented_replay", {})
        if real.get(key) is not None and aug.get(key) is not None:
            moves[f"real_vs_augmented_{key}_percent"] = ((real[key] - aug[key]) / abs(aug[key]) * 100
                                                         if aug[key] != 0 else None)
    rng = nom.get("peak_mu_range")
    if real.get("peak_mu") is not None and rng:
        moves["real_peak_mu_outside_nominal_replay_range"] = not (rng[0] <= real["peak_mu"] <= rng[1])
    out["curve_shift"] = moves
    return out


def replay(ctx: Context, motor, train, extra: dict, strategy: str, label: str) -> dict:
    """The TCU run on a model's speeds (+ candidate delays/quanta) with the scenario's sensor noise,
    once per seed in REPLAY_SEEDS: identification is sensitive to the noise draw, so the median
    and the spread (min, max) are reported; ``params`` are those of the run with the median peak mu."""
    runs = [replay_once(ctx, motor, train, extra, strategy, seed) for seed in REPLAY_SEEDS]
    out = {"source": label, "seeds": list(REPLAY_SEEDS),
           "identified_fraction": float(np.mean([r["identified"] for r in runs]))}
    for key in ("rt_percent", "peak_mu", "peak_creep_kmh", "peak_mu_err_percent", "peak_creep_err_percent",
                "t_det_s"):
        vals = np.array([r.get(key) if r.get(key) is not None else np.nan for r in runs], float)
        ok = vals[np.isfinite(vals)]
        out[key] = float(np.median(ok)) if ok.size else None
        out[f"{key}_range"] = [float(ok.min()), float(ok.max())] if ok.size else None
    with_peak = [r for r in runs if r.get("peak_mu") is not None]
    if with_peak:
        mid = sorted(with_peak, key=lambda r: r["peak_mu"])[len(with_peak) // 2]
        out["params"] = mid["params"]
    else:
        out["params"] = None
    out["identified"] = out["identified_fraction"] >= 0.5
    return out


def replay_once(ctx: Context, motor, train, extra: dict, strategy: str, seed: int) -> dict:
    d, sc = ctx.data, ctx.scenario
    sens = SensorModel(sc.sensors, seed)
    m = shift(motor, extra.get("sensor_delay", 0.0))
    v = shift(train, extra.get("sensor_delay", 0.0))
    meas = np.array([sens.measure(a, b) for a, b in zip(m, v)])
    q = extra.get("quanta", {})
    if q.get("motor_quantum_rad_s"):
        meas[:, 0] = np.round(meas[:, 0] / q["motor_quantum_rad_s"]) * q["motor_quantum_rad_s"]
    if q.get("train_quantum_ms"):
        meas[:, 1] = np.round(meas[:, 1] / q["train_quantum_ms"]) * q["train_quantum_ms"]
    cd = extra.get("can_delay", 0.0)
    tcu_m, tcu_v = shift(meas[:, 0], cd), shift(meas[:, 1], cd)
    if "can_frames" in extra:
        tcu_m, tcu_v = meas[extra["can_frames"], 0], meas[extra["can_frames"], 1]
    # offline: no deadline for the drill to keep code warm for, and it changes no result
    ident = TractionIdentifier(dataclasses.replace(sc.identifier_settings(), drill_particles=0), strategy, seed)
    events = []
    for k in range(d.n):
        out = ident.on_sensor(SensorReading(int(d.step[k]), float(tcu_m[k]), float(tcu_v[k])))
        events.extend({"t_s": e.t_s, "kind": e.kind, "params": list(e.params)} for e in out.events)
    return outcome(ctx, events, ctx.observer.creep_kmh(meas[:, 0], meas[:, 1]))
