"""``hil bench plant``: the plant alone, as a multiple of real time, and the loop's speed."""
from __future__ import annotations

import json
import time

from ..config import load_scenario


def register(sub) -> None:
    p = sub.add_parser("plant", help="plant speed alone and in the in-process loop, as multiples of real time")
    p.add_argument("scenario", nargs="?", default="scenarios/ffcc_a.toml")
    p.add_argument("--sim-seconds", type=float, default=20.0, help="simulated time per measurement")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_plant)


def measure_plant(scenario, sim_seconds: float) -> dict:
    from plant import WheelsetPlant

    cfg = scenario.plant_config()
    plant = WheelsetPlant(cfg)
    steps = int(round(sim_seconds / cfg.exchange_period_s))
    torque = plant.equilibrium_torque_nm
    t0 = time.perf_counter()
    for _ in range(steps):
        plant.step(torque)
    wall = time.perf_counter() - t0
    return {"plant_sim_s": sim_seconds, "plant_wall_s": wall, "plant_x_realtime": sim_seconds / wall,
            "plant_us_per_period": wall / steps * 1e6, "integration_steps_per_period": cfg.substeps}


def cmd_plant(args) -> int:
    from ..exchange import run

    scenario = load_scenario(args.scenario, {"run.fault_time_s": args.sim_seconds * 2,
                                             "run.duration_s": args.sim_seconds * 2 + 1})
    out = measure_plant(scenario, args.sim_seconds)
    loop_scenario = load_scenario(args.scenario)
    summary = run(loop_scenario, bus="inprocess", record=False, progress=False, log=lambda text: None)
    out["loop_inprocess_x_realtime"] = summary["sim_s"] / summary["wall_s"]
    if args.json:
        print(json.dumps(out))
    else:
        print(f"plant alone: {out['plant_sim_s']:.1f} s simulated in {out['plant_wall_s']:.2f} s = "
              f"{out['plant_x_realtime']:.1f}x real time ({out['plant_us_per_period']:.1f} us per "
              f"{out['integration_steps_per_period']}-step period)")
        print(f"in-process loop with identifier, no recording: {out['loop_inprocess_x_realtime']:.1f}x real time")
    return 0
