"""``hil bench period``: the account of an exchange period (``hil.period_account``), part by part on each
side, beside the plant alone's speed and the same run's speed without the account, all in one run."""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

from ..config import load_scenario, parse_set
from .. import terminal


def register(sub) -> None:
    p = sub.add_parser("period", help="where each microsecond of an exchange period goes, on each side, beside "
                       "the plant alone's speed and the loop's")
    p.add_argument("scenario", nargs="?", default="scenarios/ffcc_a.toml")
    p.add_argument("--strategy", default=None, help="the TCU's strategy (default: the default strategy)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--bus", default="local", help="the bus (default local: two processes)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    p.add_argument("--seconds", type=float, default=5.0, help="simulated seconds of each run (fault 0.5 s "
                   "before the end; default 5)")
    p.add_argument("--runs", type=int, default=1,
                   help="runs without the account (the loop's speed), taken in turns with the runs with it")
    p.add_argument("--plant-seconds", type=float, default=10.0, help="simulated seconds of the plant alone")
    p.add_argument("--doc", metavar="DIR", default=None, help="also write DIR/<doc-name>.md and .json")
    p.add_argument("--doc-name", default="period")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="scenario override (all runs)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_period)


def _scenario(args):
    d = args.seconds
    sets = list(args.set or []) + [f"run.duration_s={d}", f"run.fault_time_s={max(d - 0.5, d / 2)}"]
    return load_scenario(args.scenario, parse_set(sets)), sets


def run_plain(args, strategy: str, out_dir: str) -> dict:
    """One run as ``hil run`` makes it (no account): its speed and identification."""
    from ..exchange import run

    scenario, sets = _scenario(args)
    s = run(scenario, strategy, args.seed, bus=args.bus, mode=args.mode, out_dir=out_dir, progress=False,
            set_args=sets, log=lambda text: None)
    return {"speed": s["sim_s"] / s["wall_s"], "identified": s.get("identified"),
            "t_identified_s": s.get("t_identified_s"), "corrections": s.get("corrections"), "params": s.get("params"),
            "missed_per_10k": (s["missed_deadlines"] * 1e4 / s["steps"]) if s.get("steps") else None,
            "jitter_p99_us": s.get("jitter_p99_us"), "round_trip_p50_us": s.get("round_trip_p50_us"),
            "load": os.getloadavg()[0]}


def run_accounted(args, strategy: str, out_dir: str) -> dict:
    """One run with the account on both sides (``hil.period_account``): the parts' per-period times."""
    import numpy as np

    from ..exchange import exchange
    from ..period_account import ACCOUNT_ENV, install_plant
    from ..session import Session

    scenario, sets = _scenario(args)
    tcu_file = Path(out_dir) / "tcu-account.npz"
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    os.environ[ACCOUNT_ENV] = str(tcu_file)
    try:
        with Session(scenario, strategy, args.seed, bus=args.bus, mode=args.mode, external_tcu=False,
                     out_dir=out_dir, record=True, set_args=sets, plant=None, plant_label=None,
                     log=lambda text: None) as session:
            acc = install_plant(session.node, session.scenario.steps + 100)
            wall0 = time.perf_counter()
            try:
                timing = exchange(session.node, session.scenario.steps, args.mode)
            finally:
                acc.close()
            wall = time.perf_counter() - wall0
            summary = session.finish(timing, wall, None)
    finally:
        os.environ.pop(ACCOUNT_ENV, None)
    plant_parts, plant_names, plant_total = acc.table()
    out = {"speed": summary["sim_s"] / summary["wall_s"], "load": os.getloadavg()[0],
           "plant": _side(plant_parts, plant_names, plant_total)}
    if tcu_file.exists():
        z = np.load(tcu_file)
        skip = 10
        out["tcu"] = _side(z["parts"][skip:-1], [str(x) for x in z["names"]], z["total"][skip:-1])
        stamps = {k: z[k] for k in z.files if k.startswith(("sent", "received"))}
        plant = {f"{kind}_{fid:x}": np.frombuffer(a, dtype=np.int64) for fid, d in acc.stamps.items()
                 for kind, a in d.items()}
        sensor_sent = _first(plant, "sent_100")
        sensor_got = _first(stamps, "received_100")
        command_sent = _first(stamps, "sent_110")
        command_got = _first(plant, "received_110")
        # the command of step k answers the sensor frame of step k: their keys differ, their order does not
        steps = sorted(set(sensor_sent) & set(sensor_got))[skip:]
        legs = {"sensor (plant send -> TCU recv)": [sensor_got[k] - sensor_sent[k] for k in steps]}
        cmd_keys = sorted(set(command_sent) & set(command_got))[skip:]
        legs["command (TCU send -> plant recv)"] = [command_got[k] - command_sent[k] for k in cmd_keys]
        # both frames begin with their step (32 bits): the TCU's answer, and the round trip, step by step
        got_by_step = {k & 0xFFFFFFFF: t for k, t in sensor_got.items()}
        sent_by_step = {k & 0xFFFFFFFF: t for k, t in sensor_sent.items()}
        cmd_sent_by_step = {k & 0xFFFFFFFF: t for k, t in command_sent.items()}
        cmd_got_by_step = {k & 0xFFFFFFFF: t for k, t in command_got.items()}
        answered = sorted(set(got_by_step) & set(cmd_sent_by_step))[skip:]
        legs["TCU: sensor recv -> command sent"] = [cmd_sent_by_step[k] - got_by_step[k] for k in answered]
        trips = sorted(set(sent_by_step) & set(cmd_got_by_step))[skip:]
        legs["round trip (sensor sent -> command received)"] = [cmd_got_by_step[k] - sent_by_step[k] for k in trips]
        out["transit"] = {k: _stats(np.array(v, dtype=float) / 1e3) for k, v in legs.items()}
    return out


def _first(stamps: dict, name: str) -> dict:
    """key -> time of the first frame with that key (a frame sent again keeps its first time)."""
    out = {}
    kind, fid = name.split("_")
    for key, t in zip(stamps.get(f"{kind}_key_{fid}", ()), stamps.get(name, ())):
        out.setdefault(int(key), int(t))
    return out


def _stats(x) -> dict:
    import numpy as np

    x = np.asarray(x, dtype=float)
    if not len(x):
        return {"median_us": None, "p99_us": None, "mean_us": None}
    return {"median_us": float(np.median(x)), "p99_us": float(np.percentile(x, 99)), "mean_us": float(np.mean(x))}


def _side(parts, names, total) -> dict:
    return {"periods": int(len(total)), "period": _stats(total),
            "parts": {name: _stats(parts[:, i]) for i, name in enumerate(names)}}


def cmd_period(args) -> int:
    from identifier import DEFAULT_STRATEGY

    from .plant import measure_plant

    strategy = args.strategy or DEFAULT_STRATEGY
    scenario, sets = _scenario(args)
    result = {"scenario": args.scenario, "strategy": strategy, "seed": args.seed, "bus": args.bus, "mode": args.mode,
              "seconds": args.seconds, "sets": list(args.set or []), "cpus": os.cpu_count(),
              "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()), "plain": [], "accounted": []}
    say = (lambda text: print(f"bench period: {text}", file=sys.stderr, flush=True))
    with tempfile.TemporaryDirectory() as tmp:
        alone = load_scenario(args.scenario, {"run.fault_time_s": args.plant_seconds * 2,
                                              "run.duration_s": args.plant_seconds * 2 + 1})
        p = measure_plant(alone, args.plant_seconds)
        result["plant_alone"] = {"x_realtime": p["plant_x_realtime"], "us_per_period": p["plant_us_per_period"],
                                 "load": os.getloadavg()[0]}
        say(f"plant alone {p['plant_x_realtime']:.1f}x ({p['plant_us_per_period']:.1f} us a period), load "
            f"{os.getloadavg()[0]:.2f}")
        for i in range(max(args.runs, 1)):
            r = run_plain(args, strategy, f"{tmp}/plain-{i}")
            result["plain"].append(r)
            say(f"{args.mode} {args.bus} {strategy}, no account: {r['speed']:.2f}x, load {r['load']:.2f}")
            a = run_accounted(args, strategy, f"{tmp}/acc-{i}")
            result["accounted"].append(a)
            say(f"{args.mode} {args.bus} {strategy}, with the account: {a['speed']:.2f}x, load {a['load']:.2f}")
        # the plant alone once more at the end: the host's speed moved meanwhile or not
        p2 = measure_plant(alone, args.plant_seconds)
        result["plant_alone_after"] = {"x_realtime": p2["plant_x_realtime"], "load": os.getloadavg()[0]}
    text = report(result)
    if args.json:
        print(json.dumps(result))
    else:
        print(text)
    if args.doc:
        d = Path(args.doc)
        d.mkdir(parents=True, exist_ok=True)
        (d / f"{args.doc_name}.json").write_text(json.dumps(result, indent=1) + "\n")
        (d / f"{args.doc_name}.md").write_text(markdown(result, args))
    return 0


def _median(xs):
    xs = sorted(x for x in xs if x is not None)
    return xs[len(xs) // 2] if xs else None


def _fmt(x, spec=".1f"):
    return "-" if x is None else format(x, spec)


def _rows(side: dict) -> list[list[str]]:
    mean_total = side["period"]["mean_us"] or 1.0
    rows = []
    for name, s in side["parts"].items():
        rows.append([name, _fmt(s["median_us"]), _fmt(s["p99_us"]), _fmt(s["mean_us"]),
                     f"{100 * (s['mean_us'] or 0) / mean_total:.0f} %"])
    s = side["period"]
    rows.append(["period", _fmt(s["median_us"]), _fmt(s["p99_us"]), _fmt(s["mean_us"]), "100 %"])
    return rows


#: issue 52's lockstep target: the loop at least this many times real time where the plant alone runs at least
#: PLANT_ALONE_X (two processes, the default strategy)
TARGET_LOCKSTEP_X, PLANT_ALONE_X = 10.0, 130.0


def target_lines(result: dict) -> list[str]:
    """The lockstep target judged (lockstep only): the loop's median speed without the account, beside the
    plant alone's before and after the runs."""
    if result["mode"] != "lockstep":
        return []
    loop = _median([r["speed"] for r in result["plain"]])
    alone = [result["plant_alone"]["x_realtime"], result["plant_alone_after"]["x_realtime"]]
    met = "met" if loop >= TARGET_LOCKSTEP_X else "missed"
    where = "" if min(alone) >= PLANT_ALONE_X else f" (the plant alone below {PLANT_ALONE_X:g}x here)"
    return [f"  target: lockstep >= {TARGET_LOCKSTEP_X:g}x where the plant alone runs >= {PLANT_ALONE_X:g}x: "
            f"{met}, {loop:.2f}x = {100 * loop / max(alone):.1f} % of the plant alone's {max(alone):.1f}x{where}"]


def report(result: dict) -> str:
    head = ["part", "median us", "p99 us", "mean us", "of the mean period"]
    a = result["accounted"][-1]
    plain = [r["speed"] for r in result["plain"]]
    alone = result["plant_alone"]["x_realtime"]
    out = [f"{result['scenario']} {result['strategy']} seed {result['seed']}, {result['mode']} over {result['bus']}, "
           f"{result['seconds']:g} s runs, {result['date_utc']} UTC",
           f"  plant alone {alone:.1f}x real time ({result['plant_alone']['us_per_period']:.1f} us a period; "
           f"{result['plant_alone_after']['x_realtime']:.1f}x after the runs; load "
           f"{result['plant_alone']['load']:.2f})",
           f"  the loop, no account: {', '.join(f'{x:.2f}x' for x in plain)} (median {_median(plain):.2f}x; loads "
           + ", ".join(f"{r['load']:.1f}" for r in result["plain"]) + ")",
           "  the loop, with the account: " + ", ".join(f"{r['speed']:.2f}x" for r in result["accounted"]),
           *target_lines(result), "",
           f"plant side ({a['plant']['periods']} periods, the last accounted run):",
           terminal.columns(head, _rows(a["plant"]), indent="  ")]
    if "tcu" in a:
        out += ["", f"TCU side ({a['tcu']['periods']} periods):", terminal.columns(head, _rows(a["tcu"]), indent="  "),
                "", "frames in transit (send returns -> recv returns, CLOCK_MONOTONIC of both processes):",
                terminal.columns(["leg", "median us", "p99 us", "mean us"],
                                 [[k, _fmt(v["median_us"]), _fmt(v["p99_us"]), _fmt(v["mean_us"])]
                                  for k, v in a["transit"].items()], indent="  ")]
    return "\n".join(out)


def markdown(result: dict, args) -> str:
    cmd = (f"hil bench period {result['scenario']} --strategy {result['strategy']} --seed {result['seed']} --bus "
           f"{result['bus']} --mode {result['mode']} --seconds {result['seconds']:g} --runs {len(result['plain'])}"
           + "".join(f" --set {x}" for x in result["sets"]) + f" --doc {args.doc}"
           + (f" --doc-name {args.doc_name}" if args.doc_name != "period" else ""))
    return (f"# The period's account\n\nWritten by `{cmd}` on {result['date_utc']} UTC ({result['cpus']} CPUs, "
            f"load average beside each run). How it is measured: [the period's account]"
            f"(../design/lockstep.md#the-periods-account).\n\n```\n{report(result)}\n```\n")
