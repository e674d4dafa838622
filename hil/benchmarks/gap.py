"""``hil bench gap``: the blind check of the gap diagnosis.

K real runs, each with ONE effect drawn at random (seeded) with random parameters in realistic
ranges -- most from the candidate library, some (``--outside`` fraction) from effects the diagnosis
does not offer (torque ripple, wheel-radius error).  Each run is recorded to MCAP, diagnosed through
``hil.gap.read_real_log`` (which drops the truth key), and only then compared with the truth read
from the log's ``reality_truth`` metadata.

Not drawn: ``torque_lag``.  The TCU commands a constant torque, so a first-order torque lag never
acts and no diagnosis can see it (the gap is zero); it stays in the library and among the candidates.
"""
from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..sweep.engine import map_in_order

#: drawn effect -> (the parameter the diagnosis must recover, sampler(rng) -> params)
LIBRARY = {
    "load_transfer": ("bogie_height_m", lambda g: {"bogie_height_m": g.uniform(0.5, 2.6)}),
    "compliance": ("stiffness_nm_rad", lambda g: {"stiffness_nm_rad": math.exp(g.uniform(math.log(1e5), math.log(1e6))),
                                                  "damping_ratio": g.uniform(0.02, 0.15),
                                                  "backlash_rad": g.uniform(0.0, 0.002)}),
    "adhesion_lag": ("tau_s", lambda g: {"tau_s": math.exp(g.uniform(math.log(0.003), math.log(0.03)))}),
    "resistance": ("factor", lambda g: {"factor": g.uniform(0.4, 0.7) if g.random() < 0.5 else g.uniform(1.4, 2.0)}),
    "sensor_delay": ("delay_ms", lambda g: {"delay_ms": g.uniform(1.0, 8.0)}),
    "sensor_quantisation": ("motor_quantum_rad_s",
                            lambda g: {"motor_quantum_rad_s": math.exp(g.uniform(math.log(0.04), math.log(0.2)))}),
    "can": ("delay_ms", lambda g: {"delay_ms": float(g.integers(1, 7)), "jitter_ms": g.uniform(0.0, 1.0),
                                   "loss": g.uniform(0.0, 0.03)}),
}
OUTSIDE = {
    "torque_ripple": lambda g: {"amplitude": g.uniform(0.01, 0.05), "frequency_hz": g.uniform(20.0, 150.0),
                                "phase_rad": g.uniform(0, 2 * math.pi)},
    "wheel_radius": lambda g: {"error_percent": float(g.choice([-1, 1]) * g.uniform(0.05, 0.3))},
}


def register(sub) -> None:
    p = sub.add_parser("gap", help="blind check of hil gap on runs with one random hidden effect each")
    p.add_argument("scenario", nargs="?", default="scenarios/ffcc_a.toml")
    p.add_argument("--cases", type=int, default=24, help="number of real runs (default 24)")
    p.add_argument("--seed", type=int, default=1, help="seed of the effect and parameter draws")
    p.add_argument("--outside", type=float, default=0.25,
                   help="fraction of cases whose effect is outside the candidate list (default 0.25)")
    p.add_argument("--out", default=None, help="keep the MCAP logs here (default: a temporary directory)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None, help="run the cases on this Dask cluster "
                   "(tcp://HOST:PORT; hil sweep's engine)")
    p.add_argument("--workers", type=int, default=None, help="run the cases on a local Dask cluster of this many "
                   "worker processes (default: serially in this process)")
    p.set_defaults(func=cmd_gap_bench)


def draw_case(seed: int, i: int, outside_fraction: float) -> tuple[str, dict, int]:
    """(effect, params, run seed) of case i: a pure function of (seed, i)."""
    g = np.random.default_rng([seed, i, 0x6A9])
    if g.random() < outside_fraction:
        name = sorted(OUTSIDE)[int(g.integers(len(OUTSIDE)))]
        params = OUTSIDE[name](g)
    else:
        name = sorted(LIBRARY)[int(g.integers(len(LIBRARY)))]
        params = LIBRARY[name][1](g)
    return name, params, int(g.integers(1, 2 ** 31 - 1))


def truth_value(effect: str, truth: dict) -> float | None:
    """The parameter value the diagnosis must recover, from the log's truth record."""
    if effect not in LIBRARY:
        return None
    params = json.loads(truth["effects"])[effect]
    if effect == "can":   # the TCU sees whole periods: the realised mean delay is the recoverable figure
        return json.loads(truth["can_realised"])["mean_delay_ms"]
    return params[LIBRARY[effect][0]]


def run_case(scenario, effect: str, params: dict, run_seed: int, out_dir: Path, i: int) -> dict:
    from ..gap import diagnose, read_real_log
    from ..logread import read_log
    from ..exchange import run
    from ..effects import TRUTH_KEY, with_reality

    real = with_reality(scenario, {effect: params})
    summary = run(real, "nlls", run_seed, bus="inprocess", out_dir=out_dir / f"case{i:03d}", progress=False,
                  log=lambda text: None)
    path = summary["mcap"]
    t0 = time.perf_counter()
    out, _ = diagnose(read_real_log(path), scenario, identify=False)   # blind: no truth in here
    wall = time.perf_counter() - t0
    truth = read_log(path).metadata[TRUTH_KEY]                          # only now, for scoring
    named = out["which"]["named"]
    expected = effect if effect in LIBRARY else "none"
    rec = {"case": i, "effect": effect, "params": params, "expected": expected, "named": named,
           "correct": named == expected, "shrink_percent": out["shrink"]["held_out_gap_shrink_percent"],
           "nominal_gap": out["which"]["nominal_held_out_gap"], "best": out["which"]["ranking"][0]["effect"],
           "best_gap": out["which"]["ranking"][0]["held_out_gap"],
           "best_gap_own_floor": out["which"]["ranking"][0]["held_out_gap_own_floor"], "diagnosis_s": wall, "log": path}
    if effect in LIBRARY:
        true_v = truth_value(effect, truth)
        rec["true_value"] = true_v
        if named == effect:
            fitted = out["which"]["ranking"][0]["params"][LIBRARY[effect][0]]
            rec["fitted_value"] = fitted
            rec["param_err_percent"] = abs(fitted - true_v) / abs(true_v) * 100
    return rec


def gap_case(job) -> dict:
    """Case ``i``: draw its effect, make the real run, diagnose it blind, score it.  Plain data in and out,
    so it runs on a Dask worker as well as here; the log goes to ``out/case<i>`` when ``out`` is given
    (on the machine that runs the case), else to a temporary directory removed after the case."""
    scenario, seed, i, outside, out = job
    effect, params, run_seed = draw_case(seed, i, outside)
    if out:
        return run_case(scenario, effect, params, run_seed, Path(out), i)
    with tempfile.TemporaryDirectory(prefix="hil-gap-bench-") as tmp:
        return run_case(scenario, effect, params, run_seed, Path(tmp), i)


def summarise(records: list[dict]) -> dict:
    lib = [r for r in records if r["expected"] != "none"]
    out_ = [r for r in records if r["expected"] == "none"]
    labels = sorted({r["expected"] for r in records} | {r["named"] for r in records})
    confusion = {e: {n: 0 for n in labels} for e in labels if any(r["expected"] == e for r in records)}
    for r in records:
        confusion[r["expected"]][r["named"]] += 1
    shrinks = [r["shrink_percent"] for r in lib if r["correct"]]
    perr = [r["param_err_percent"] for r in lib if "param_err_percent" in r]
    per_class = {e: sum(r["correct"] for r in lib if r["expected"] == e) / max(1, sum(r["expected"] == e for r in lib))
                 for e in sorted({r["expected"] for r in lib})}
    return {
        "cases": len(records), "library_cases": len(lib), "outside_cases": len(out_),
        "effect_classes": len(per_class),
        "top1_accuracy": sum(r["correct"] for r in lib) / len(lib) if lib else None,
        "none_accuracy": sum(r["correct"] for r in out_) / len(out_) if out_ else None,
        "median_shrink_percent": float(np.median(shrinks)) if shrinks else None,
        "median_param_err_percent": float(np.median(perr)) if perr else None,
        "param_within_20_percent": sum(p <= 20 for p in perr) / len(perr) if perr else None,
        "per_class_accuracy": per_class,
        "confusion": confusion,
        "median_diagnosis_s": float(np.median([r["diagnosis_s"] for r in records])) if records else None,
    }


def cmd_gap_bench(args) -> int:
    from ..errors import ConfigError
    from ..config import load_scenario

    if args.cases < 1:
        raise ConfigError(f"--cases {args.cases}: must be >= 1")
    if not 0 <= args.outside <= 1:
        raise ConfigError(f"--outside {args.outside}: must be in [0, 1]")
    scenario = load_scenario(args.scenario)
    records = []
    wall0 = time.perf_counter()
    jobs = [(scenario, args.seed, i, args.outside, args.out) for i in range(args.cases)]

    # one case per call, serially here or on Dask (--scheduler / --workers): the same records either way
    for rec in map_in_order(gap_case, jobs, args.scheduler, args.workers,
                            lambda done, i: print(f"hil bench gap: {done}/{args.cases} cases done (case {i})",
                                                  file=sys.stderr, flush=True)):
        records.append(rec)
        extra = f" param err {rec['param_err_percent']:.1f} %" if "param_err_percent" in rec else ""
        print(f"hil bench gap: case {rec['case'] + 1}/{args.cases}: {rec['effect']} -> {rec['named']} "
              f"({'ok' if rec['correct'] else 'WRONG'}), shrink {rec['shrink_percent']:.0f} %{extra}",
              file=sys.stderr, flush=True)
    result = summarise(records)
    result.update({"seed": args.seed, "scenario": scenario.path, "wall_s": time.perf_counter() - wall0,
                   "records": [{k: v for k, v in r.items() if k != "log" or args.out} for r in records]})
    if args.json:
        print(json.dumps(result))
    else:
        print(f"gap bench: {result['cases']} cases (seed {args.seed}), {result['effect_classes']} effect classes")
        from ..trace import fmt as f
        print(f"  top-1 accuracy {f(result['top1_accuracy'], '.3f')} ({result['library_cases']} library cases)  "
              f"'none' accuracy {f(result['none_accuracy'], '.3f')} ({result['outside_cases']} outside)")
        print(f"  median held-out gap shrink {f(result['median_shrink_percent'], '.1f')} %  "
              f"median parameter error {f(result['median_param_err_percent'], '.2f')} %  "
              f"(within 20 %: {f(result['param_within_20_percent'], '.3f')})")
        print("  confusion (rows: truth, columns: named):")
        cols = sorted({n for row in result["confusion"].values() for n, c in row.items()})
        print("    " + " " * 20 + " ".join(f"{c[:8]:>8s}" for c in cols))
        for e, row in result["confusion"].items():
            print(f"    {e:20s}" + " ".join(f"{row.get(c, 0):8d}" for c in cols))
    return 0
