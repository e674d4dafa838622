"""``hil bench fmu``: our FMU against the CasADi plant -- deviation, identification, cost per step, loop speed."""
from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ..config import load_scenario
from .. import terminal

STATE_FIELDS = ("motor_speed_rad_s", "train_speed_ms", "creep_speed_kmh", "mu", "load_torque_nm")
#: summary keys that depend on the wall clock, not on the run
_TIMING_KEYS = {"wall_s", "mcap", "sim_s_per_wall_s", "messages", "frames_tx", "frames_rx"}


def register(sub) -> None:
    p = sub.add_parser("fmu", help="exported FMU vs CasADi plant: deviation, identification, step cost, loop speed")
    p.add_argument("scenarios", nargs="*", default=["scenarios/ffcc_a.toml", "scenarios/ffcc_b.toml"])
    p.add_argument("--sim-seconds", type=float, default=20.0, help="simulated time per step-cost measurement")
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_fmu)


def _step_cost_us(plant, steps: int) -> float:
    torque = plant.equilibrium_torque_nm
    plant.reset()
    t0 = time.perf_counter()
    for _ in range(steps):
        plant.step(torque)
    return (time.perf_counter() - t0) / steps * 1e6


def _deviation(scenario, fmu_path) -> dict:
    """Max |FMU - CasADi| per output over the whole scenario, under a moving torque."""
    from plant import WheelsetPlant
    from plant.fmu_plant import FmuPlant

    cfg = scenario.plant_config()
    ref = WheelsetPlant(cfg)
    k = np.arange(scenario.steps)
    torques = ref.equilibrium_torque_nm * (1 + 0.2 * np.sin(k / 37) + 0.05 * (k > scenario.steps // 3)) \
        + np.random.default_rng(0).normal(0, 30, scenario.steps)
    worst = dict.fromkeys(STATE_FIELDS, 0.0)
    with FmuPlant(fmu_path, cfg) as fmu:
        for tq in torques:
            a, b = ref.step(tq), fmu.step(tq)
            for name in STATE_FIELDS:
                worst[name] = max(worst[name], abs(getattr(a, name) - getattr(b, name)))
    return worst


def cmd_fmu(args) -> int:
    import fmpy
    from fmpy.validation import validate_fmu

    from plant import WheelsetPlant
    from plant.fmu import export_fmu, parameter_values
    from plant.fmu_plant import FmuPlant

    from ..exchange import run
    from ..plants import plant_label

    out: dict = {"scenarios": {}}
    with tempfile.TemporaryDirectory(prefix="hil-bench-fmu-") as tmp:
        first = load_scenario(args.scenarios[0])
        t0 = time.perf_counter()
        fmu_path = export_fmu(first.plant_config(), Path(tmp) / "wheelset.fmu", stop_time_s=first.run.duration_s)
        out["export_s"] = time.perf_counter() - t0
        out["validation_problems"] = validate_fmu(str(fmu_path))
        for path in args.scenarios:
            sc = load_scenario(path)
            cfg = sc.plant_config()
            r: dict = {"max_abs_deviation": _deviation(sc, fmu_path)}
            res = fmpy.simulate_fmu(str(fmu_path), stop_time=sc.run.duration_s, step_size=cfg.exchange_period_s,
                                    output_interval=cfg.exchange_period_s, start_values=parameter_values(cfg, 2),
                                    output=list(STATE_FIELDS))
            ref = WheelsetPlant(cfg)
            states = [ref.state] + [ref.step(ref.equilibrium_torque_nm) for _ in range(sc.steps)]
            r["simulate_fmu_max_abs_deviation"] = {
                name: float(np.max(np.abs(res[name] - np.array([getattr(s, name) for s in states]))))
                for name in STATE_FIELDS}
            summaries = {}
            for kind in ("casadi", "fmu"):
                plant = FmuPlant(fmu_path, cfg) if kind == "fmu" else None
                try:
                    summaries[kind] = run(sc, "nlls", args.seed, bus="inprocess", record=False, progress=False,
                                             plant=plant, plant_label=plant_label(plant), log=lambda text: None)
                finally:
                    if plant is not None:
                        plant.close()
                r[f"loop_{kind}_x_realtime"] = summaries[kind]["sim_s"] / summaries[kind]["wall_s"]
            a, b = summaries["casadi"], summaries["fmu"]
            r["identification_identical"] = all(a.get(k) == b.get(k) for k in set(a) | set(b) if k not in _TIMING_KEYS)
            r["identified"], r["params"] = a["identified"], a["params"]
            out["scenarios"][sc.name] = r
        long = load_scenario(args.scenarios[0], {"run.fault_time_s": args.sim_seconds * 2,
                                                 "run.duration_s": args.sim_seconds * 2 + 1})
        steps = int(round(args.sim_seconds / long.run.exchange_period_s))
        with FmuPlant(fmu_path, long.plant_config()) as fmu:
            out["fmu_us_per_step"] = _step_cost_us(fmu, steps)
        fmu3_path = export_fmu(first.plant_config(), Path(tmp) / "wheelset3.fmu", fmi_version=3)
        out["fmi3_validation_problems"] = validate_fmu(str(fmu3_path))
        out["fmi3_max_abs_deviation"] = {sc_path: max(_deviation(load_scenario(sc_path), fmu3_path).values())
                                         for sc_path in args.scenarios}
        with FmuPlant(fmu3_path, long.plant_config()) as fmu:
            out["fmu3_us_per_step"] = _step_cost_us(fmu, steps)
        out["casadi_us_per_step"] = _step_cost_us(WheelsetPlant(long.plant_config()), steps)
        out["steps_measured"] = steps
    if args.json:
        print(json.dumps(out))
        return 0
    say = lambda text: print(terminal.wrap(text, indent="    ", first=""))  # noqa: E731
    say(f"export (CasADi codegen + gcc + zip): {out['export_s']:.2f} s; fmpy.validation: "
        f"{out['validation_problems'] or 'no problems'}")
    say(f"cost per plant step ({steps} steps, 1 exchange period each): FMU {out['fmu_us_per_step']:.1f} us, "
        f"CasADi {out['casadi_us_per_step']:.1f} us, FMI 3.0 FMU {out['fmu3_us_per_step']:.1f} us")
    say(f"FMI 3.0 export: fmpy.validation {out['fmi3_validation_problems'] or 'no problems'}; max |FMU - CasADi| "
        + ", ".join(f"{k} {v:.3g}" for k, v in out["fmi3_max_abs_deviation"].items()))
    for name, r in out["scenarios"].items():
        dev = max(r["max_abs_deviation"].values())
        dev_sim = max(r["simulate_fmu_max_abs_deviation"].values())
        say(f"{name}: max |FMU - CasADi| {dev:.3g} (FmuPlant, moving torque), {dev_sim:.3g} (fmpy.simulate_fmu); "
            f"identification identical: {r['identification_identical']}; loop {r['loop_casadi_x_realtime']:.1f}x "
            f"real time with CasADi, {r['loop_fmu_x_realtime']:.1f}x with the FMU")
    return 0
