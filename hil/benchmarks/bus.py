"""``hil bench bus``: the same lockstep run over several buses (identical frames? identical
identification? simulated seconds per wall second), and optionally a real-time run's timing."""
from __future__ import annotations

import hashlib
import json
import sys
import tempfile

from ..config import load_scenario
from .judge import _median

IDENT_KEYS = ("identified", "t_identified_s", "corrections", "params", "samples", "mse", "r2", "observer_lag_ms")
HEARTBEAT_IDS = (0x701, 0x702)


def register(sub) -> None:
    p = sub.add_parser("bus", help="lockstep over several buses: identical frames and identification, speed; "
                       "optionally real time")
    p.add_argument("scenario", nargs="?", default="scenarios/ffcc_a.toml")
    p.add_argument("--buses", default="inprocess,hub,auto", help="comma-separated bus specs (default "
                   "inprocess,hub,auto)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--strategy", default=None,
                   help="the TCU's strategy (default: proposed for --realtime-runs, the real-time issue's "
                   "measure; nlls otherwise)")
    p.add_argument("--realtime-seconds", type=float, default=0.0,
                   help="also run this many seconds in real time over --realtime-bus (fault 0.5 s before the end)")
    p.add_argument("--realtime-bus", default="hub")
    p.add_argument("--realtime-runs", type=int, default=0,
                   help="instead: this many real-time runs (each --realtime-seconds long, default 5) per bus of "
                   "--realtime-buses, each a `hil run --mode realtime --json` process, and a lockstep run per bus "
                   "(1 ms period, strategy proposed) for its speed")
    p.add_argument("--realtime-buses", default="local,hub,inprocess")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE", help="scenario override (all runs)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_bus)


def stream_digest(mcap_path) -> dict:
    """sha256 of the (id, payload) sequence of valid non-heartbeat frames, sent and received."""
    from ..logread import read_log

    frames = read_log(mcap_path, {"/can/frames"}).topic("/can/frames")
    out = {}
    for direction in ("tx", "rx"):
        h = hashlib.sha256()
        n = 0
        for f in frames:
            if f.direction == direction and f.status == "ok" and f.arbitration_id not in HEARTBEAT_IDS:
                h.update(f.arbitration_id.to_bytes(4, "little") + len(f.data).to_bytes(1, "little") + f.data)
                n += 1
        out[direction] = {"frames": n, "sha256": h.hexdigest()[:16]}
    return out


def _rt_run(scenario_path, bus, seconds, sets, seed, strategy, out_dir) -> dict:
    """One real-time ``hil run --json`` process: its figures, exit code, load average and whether
    SCHED_FIFO was asked for and granted (None: not asked)."""
    import os
    import subprocess

    cmd = [sys.executable, "-m", "hil.cli", "run", str(scenario_path), "--mode", "realtime", "--bus", bus,
           "--strategy", strategy, "--seed", str(seed), "--out", out_dir, "--json",
           "--set", f"run.duration_s={seconds}", "--set", f"run.fault_time_s={max(seconds - 0.5, seconds / 2)}"]
    for item in sets:
        cmd += ["--set", item]
    r = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
    try:
        s = json.loads(r.stdout) if r.stdout.strip() else {}
    except ValueError:
        s = {}
    steps = s.get("steps")
    missed = s.get("missed_deadlines")
    fifo = None
    if "SCHED_FIFO" in r.stderr:
        fifo = "cannot set SCHED_FIFO" not in r.stderr
    return {"exit_code": r.returncode, "missed_deadlines": missed,
            "missed_per_10k": missed * 1e4 / steps if missed is not None and steps else None,
            "jitter_p50_us": s.get("jitter_p50_us"), "jitter_p99_us": s.get("jitter_p99_us"),
            "jitter_max_us": s.get("jitter_max_us"), "round_trip_p50_us": s.get("round_trip_p50_us"),
            "round_trip_p99_us": s.get("round_trip_p99_us"), "tcu_stale_skipped": s.get("tcu_stale_skipped"),
            "loadavg_1min": os.getloadavg()[0], "sched_fifo_granted": fifo,
            "error": r.stderr.strip().splitlines()[-1] if r.returncode and r.stderr.strip() else None}


def cmd_realtime(args, sets) -> int:
    args.strategy = args.strategy or "proposed"
    from ..config import parse_set
    from ..exchange import run as run_can
    from ..link import resolve

    seconds = args.realtime_seconds or 5.0
    buses = [b.strip() for b in args.realtime_buses.split(",") if b.strip()]
    result = {"scenario": args.scenario, "seconds": seconds, "default_bus": resolve("auto"), "buses": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for bus in buses:
            runs = []
            for i in range(args.realtime_runs):
                print(f"bench bus: {bus} real-time run {i + 1}/{args.realtime_runs} ({seconds:g} s, {args.strategy})",
                      file=sys.stderr, flush=True)
                runs.append(_rt_run(args.scenario, bus, seconds, sets, args.seed, args.strategy, f"{tmp}/{bus}-{i}"))
                r = runs[-1]
                print(f"bench bus:   exit {r['exit_code']}, missed/10k {r['missed_per_10k']}, jitter p99 "
                      f"{r['jitter_p99_us']} us, load {r['loadavg_1min']:.2f}", file=sys.stderr, flush=True)
            print(f"bench bus: {bus} lockstep run ({seconds:g} s, proposed)", file=sys.stderr, flush=True)
            ls_sets = sets + ["run.exchange_period_s=0.001", f"run.duration_s={seconds}",
                              f"run.fault_time_s={max(seconds - 0.5, seconds / 2)}"]
            s = run_can(load_scenario(args.scenario, parse_set(ls_sets)), "proposed", args.seed, bus=bus,
                        out_dir=f"{tmp}/{bus}-ls", progress=False, set_args=ls_sets, log=lambda text: None)
            speed = s["sim_s"] / s["wall_s"]
            result["buses"][bus] = {
                "runs": runs, "exit_codes": [r["exit_code"] for r in runs],
                "missed_per_10k": _median([r["missed_per_10k"] for r in runs]),
                "jitter_p99_us": _median([r["jitter_p99_us"] for r in runs]),
                "round_trip_p99_us": _median([r["round_trip_p99_us"] for r in runs]),
                "lockstep_speed": speed}
    if args.json:
        print(json.dumps(result))
        return 0
    f = lambda x, fmt="7.0f": "      -" if x is None else format(x, fmt)  # noqa: E731
    print(f"{args.scenario}: {args.realtime_runs} real-time run(s) of {seconds:g} s per bus; auto is "
          f"{result['default_bus']} here")
    for bus, b in result["buses"].items():
        print(f"  {bus}: lockstep {b['lockstep_speed']:.2f} sim s/wall s (1 ms, proposed)")
        for r in b["runs"]:
            fifo = {None: "not asked", True: "granted", False: "REFUSED"}[r["sched_fifo_granted"]]
            print(f"    exit {r['exit_code']}  missed/10k {f(r['missed_per_10k'], '6.1f')}  jitter p50/p99/max "
                  f"{f(r['jitter_p50_us'])}/{f(r['jitter_p99_us'])}/{f(r['jitter_max_us'])} us  round trip p50/p99 "
                  f"{f(r['round_trip_p50_us'])}/{f(r['round_trip_p99_us'])} us  skipped {r['tcu_stale_skipped']}  "
                  f"load {r['loadavg_1min']:.2f}  SCHED_FIFO {fifo}" + (f"  ({r['error']})" if r["error"] else ""))
    return 0


def cmd_bus(args) -> int:
    from ..exchange import run as run_can
    from ..config import parse_set

    if args.realtime_runs > 0:
        return cmd_realtime(args, list(args.set or []))

    args.strategy = args.strategy or "nlls"
    sets = list(args.set or [])
    scenario = load_scenario(args.scenario, parse_set(sets))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, bus in enumerate(b.strip() for b in args.buses.split(",") if b.strip()):
            s = run_can(scenario, args.strategy, args.seed, bus=bus, out_dir=f"{tmp}/{i}", progress=False,
                        set_args=sets, log=lambda text: None)
            rows.append({"bus": s["bus"], "sim_s_per_wall_s": s["sim_s"] / s["wall_s"], "wall_s": s["wall_s"],
                         "round_trip_p50_us": s["round_trip_p50_us"], "round_trip_p99_us": s["round_trip_p99_us"],
                         "streams": stream_digest(s["mcap"]), "identification": {k: s[k] for k in IDENT_KEYS}})
        rt = None
        if args.realtime_seconds > 0:
            d = args.realtime_seconds
            rt_sets = sets + [f"run.duration_s={d}", f"run.fault_time_s={max(d - 0.5, 0.1)}"]
            s = run_can(load_scenario(args.scenario, parse_set(rt_sets)), args.strategy, args.seed,
                        bus=args.realtime_bus, mode="realtime", out_dir=f"{tmp}/rt", progress=False,
                        set_args=rt_sets, log=lambda text: print(text, file=sys.stderr))
            rt = {k: s.get(k) for k in ("bus", "sim_s", "wall_s", "missed_deadlines", "jitter_p99_us", "jitter_max_us",
                                        "lateness_p99_us", "round_trip_p50_us", "round_trip_p99_us", "late_commands",
                                        "identified")}
    first = rows[0]
    for r in rows:
        r["same_frames_as_first"] = r["streams"] == first["streams"]
        r["same_identification_as_first"] = r["identification"] == first["identification"]
    result = {"scenario": scenario.name, "seed": args.seed, "lockstep": rows, "realtime": rt}
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{scenario.name} seed {args.seed}, lockstep:")
    for r in rows:
        st = r["streams"]
        print(f"  {r['bus']:<18} {r['sim_s_per_wall_s']:6.2f} sim s/wall s  round trip p50 "
              f"{r['round_trip_p50_us']:7.0f} us  tx {st['tx']['frames']} frames {st['tx']['sha256']}  "
              f"rx {st['rx']['frames']} frames {st['rx']['sha256']}  same frames: "
              f"{'yes' if r['same_frames_as_first'] else 'NO'}  same identification: "
              f"{'yes' if r['same_identification_as_first'] else 'NO'}")
    ident = first["identification"]
    print(f"  identification ({first['bus']}): identified {ident['identified']} at {ident['t_identified_s']} s "
          f"after {ident['corrections']} corrections")
    if rt:
        print(f"realtime {rt['sim_s']:.1f} s over {rt['bus']}: missed deadlines {rt['missed_deadlines']}, jitter p99 "
              f"{rt['jitter_p99_us']:.0f} us (max {rt['jitter_max_us']:.0f}), round trip p50 "
              f"{rt['round_trip_p50_us']:.0f} us p99 {rt['round_trip_p99_us']:.0f} us")
    return 0
