"""``hil run SCENARIO``: one HIL run, recorded to MCAP; ``--json`` prints its summary."""
from __future__ import annotations

import json
import sys

from identifier import DEFAULT_STRATEGY, STRATEGIES

from ..config import load_scenario, parse_set
from ..errors import ConfigError
from ..trace import fmt as _fmt
from ..traction import response_text


def register(sub) -> None:
    p = sub.add_parser("run", help="run a scenario on the HIL loop and record it to MCAP")
    p.add_argument("scenario", help="scenario TOML file, e.g. scenarios/ffcc_a.toml")
    p.add_argument("--bus", default="auto", help="bus between plant and TCU: auto (socketcan:vcan0 when the kernel "
                   "has it, else local), local (the embedded relay-free bus), hub (python-can-remote on 127.0.0.1), "
                   "socketcan:<ch>, inprocess (no second process, same frames), or any python-can interface:channel "
                   "(default: auto)")
    p.add_argument("--tcu", choices=("process", "external"), default="process",
                   help="process: start the identifier as a second process (default); external: a TCU already on "
                   "the bus answers (hil tcu elsewhere, or a real TCU)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="lockstep: the plant waits for the TCU's command each period (deterministic); realtime: "
                   "paced by the wall clock, deadline misses and jitter recorded (default: lockstep)")
    p.add_argument("--strategy", default=DEFAULT_STRATEGY,
                   help=f"identification strategy ({', '.join(sorted(STRATEGIES))}; default {DEFAULT_STRATEGY})")
    p.add_argument("--seed", type=int, default=None, help="seed for sensor noise and the identifier "
                   "(default: the scenario's)")
    p.add_argument("--out", default=None, help="directory for the MCAP log (default: logs/)")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE",
                   help="override a scenario field, e.g. --set run.duration_s=600 (repeatable)")
    p.add_argument("--reality", action="append", metavar="EFFECT[:PARAM=VALUE,...]",
                   help="switch on an effect the nominal model lacks, for a 'real' run (repeatable; "
                   "see hil/effects.py, e.g. load_transfer:bogie_height_m=1.5, can:delay_ms=3)")
    p.add_argument("--plant", default=None, metavar="casadi|fmu:PATH",
                   help="plant model: the CasADi model or an FMI 2.0/3.0 Co-Simulation FMU (default: the "
                   "scenario's [plant] table, else casadi). Loading an FMU runs its native code")
    p.add_argument("--control", default=None, metavar="LAW",
                   help="the TCU's control law (demand, readhesion, constant_creep, extremum_seeking, identified; "
                   "default: the scenario's [control] law, else demand: open loop as the paper ran it)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--no-rrd", action="store_true", help="do not write the Rerun recording (.rrd) beside the log")
    p.set_defaults(func=cmd_run)


def cmd_run(args) -> int:
    if args.strategy not in STRATEGIES:
        raise ConfigError(f"unknown strategy {args.strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
    if args.control is not None:
        from identifier.control import LAWS
        if args.control not in LAWS:
            raise ConfigError(f"--control {args.control!r}: unknown control law (known: {', '.join(LAWS)})")
        args.set = [*(args.set or []), f"control.law={json.dumps(args.control)}"]
    scenario = load_scenario(args.scenario, parse_set(args.set))
    scenario = apply_reality_args(scenario, args.reality)
    from ..errors import PeerSilent
    from ..exchange import check_deadlines, run
    from ..plants import make_plant, plant_label
    from ..log.record import prepare_out_dir
    from ..progress import compile_kernels

    plant = make_plant(scenario, args.plant)   # None: the CasADi model; a refused FMU creates no --out
    try:
        prepare_out_dir(args.out)              # a bad --out is told now, not after a first-run compile
    except ConfigError:
        if plant is not None:
            plant.close()
        raise
    if args.tcu != "external":
        compile_kernels("hil run")             # the first run on a machine: shown, not a silent wait
    try:
        summary = run(scenario, args.strategy, args.seed, bus=args.bus, mode=args.mode, out_dir=args.out,
                      set_args=args.set, plant=plant, plant_label=plant_label(plant),
                      external_tcu=args.tcu == "external")
    except PeerSilent as e:
        if args.json and getattr(e, "summary", None) is not None:
            print(json.dumps(e.summary))      # still the one JSON object, with the fault in it
        raise PeerSilent(f"{e}; fault recorded, log closed") from None
    finally:
        if plant is not None:
            plant.close()
    rrd = None if args.no_rrd or not summary.get("mcap") else write_rrd_beside(summary["mcap"])
    if args.json:
        print(json.dumps(summary))
    else:
        print_summary(summary)
        if rrd:
            print(f"  rerun: {rrd}")
    sys.stdout.flush()
    check_deadlines(summary)     # real time: too many misses -> exit 5, after the logs and the summary
    return 0


def write_rrd_beside(mcap_path):
    """The Rerun recording beside the MCAP (hil view); its path on stderr; a failure only warns."""
    from ..view import write_rrd

    try:
        rrd, _ = write_rrd(mcap_path)
    except Exception as e:  # noqa: BLE001 - the run itself succeeded; the .rrd can be made later with hil view
        print(f"hil run: warning: no Rerun recording written ({type(e).__name__}: {e}); try hil view {mcap_path}",
              file=sys.stderr)
        return None
    print(f"hil run: Rerun recording {rrd}", file=sys.stderr)
    return rrd


def apply_reality_args(scenario, items):
    """``--reality EFFECT[:p=v,...]`` merged into the scenario's [reality] table (validated)."""
    from ..effects import parse_effect, with_reality
    try:
        parsed = dict(parse_effect(item) for item in items or [])
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return with_reality(scenario, parsed) if parsed else scenario


def print_summary(s: dict, file=sys.stdout, heading: str | None = None) -> None:
    """The run summary as text; every figure prints n/a where the source lacks it (e.g. a CAN log has no truth)."""
    external = s.get("transport") == "external"      # what it runs is its own: nothing to claim for it
    strategy = "(the external TCU's own)" if external else s["strategy"]
    print(heading or f"scenario {s['scenario']}  strategy {strategy}  seed {s['seed']}  bus {s['bus']}"
          + (f"  plant {s['plant']}" if s.get("plant") else "")
          + (f"  frames {'authenticated' if s['frame_auth'] == 'on' else 'not authenticated'}"
             if s.get("frame_auth") else ""), file=file)
    if s.get("reality"):
        print("  reality: " + "; ".join(f"{name}(" + ", ".join(f"{k}={v}" for k, v in (params or {}).items()) + ")"
                                        for name, params in s["reality"].items()), file=file)
    print(f"  fault at {_fmt(s['t_fault_s'], '.3f')} s, serious stage at {_fmt(s['t_serious_s'], '.3f')} s "
          f"(T_det {_fmt(s['t_det_s'] and s['t_det_s'] * 1e3, '.1f')} ms), slip detected at "
          f"{_fmt(s['t_detected_s'], '.3f')} s", file=file)
    if s["identified"]:
        print(f"  identified at {_fmt(s['t_identified_s'], '.3f')} s: RT {_fmt(s['rt_percent'], '.1f')} % after "
              f"{s['corrections']} corrections", file=file)
    elif s.get("unconfirmed"):
        print(f"  UNCONFIRMED: the TCU gave up after {s['corrections']} corrections (the data did not pin the curve)",
              file=file)
        print("  its best estimate:", file=file)
    elif external and not s.get("corrections"):
        print("  no identification result received (an external TCU need not send TcuResult frames)", file=file)
    else:
        print(f"  NOT identified within the run ({s['corrections']} corrections)", file=file)
    if s.get("params"):
        print("  params (l0, l1, l2, t1, t2): " + ", ".join(f"{x:.5g}" for x in s["params"]), file=file)
        if s.get("peak_mu_ci") and s.get("peak_creep_ci"):
            (m0, m1), (c0, c1) = s["peak_mu_ci"], s["peak_creep_ci"]
            print(f"  how sure (90 % intervals): peak mu {m0:.4f} .. {m1:.4f}, peak creep {c0:.3f} .. {c1:.3f} km/h"
                  + ("\n    (open: the peak may lie past the creeps seen; the upper ends are the TCU's range)"
                     if s.get("peak_interval_open") else ""), file=file)
        print(f"  fit: MSE {_fmt(s['mse'], '.3e')}  RMSE {_fmt(s['rmse'], '.3e')}  MAE {_fmt(s['mae'], '.3e')}  "
              f"R2 {_fmt(s['r2'], '.5f')}", file=file)
        print(f"  vs true curve: peak mu error {_fmt(s['peak_mu_err_percent'], '.2f')} %, peak creep error "
              f"{_fmt(s['peak_creep_err_percent'], '.2f')} %, R2 {_fmt(s.get('r2_vs_truth'), '.5f')} "
              f"(on 0..2x its peak creep)"
              + ("\n    its 90 % intervals MISS the true peak" if s.get("peak_ci_holds_truth") is False else ""),
              file=file)
    print(f"  observer lag {_fmt(s.get('observer_lag_ms'), '.1f')} ms; "
          f"{_fmt(s.get('sim_s'), '.2f')} s simulated in {_fmt(s.get('wall_s'), '.2f')} s", file=file)
    if s.get("adhesion_utilisation") is not None:
        print(f"  traction ({s.get('control')}): adhesion utilisation {_fmt(s['adhesion_utilisation'], '.3f')}, "
              f"where it matters {_fmt(s.get('adhesion_utilisation_low'), '.3f')}; macro-slip "
              f"{_fmt(s.get('macro_slip_s'), '.3f')} s ({s.get('macro_slip_count')}x)", file=file)
        print(f"    {response_text(s.get('reaction_ms'), s.get('recovery_s'))}, "
              f"ripple {_fmt(s.get('torque_ripple_percent'), '.2f')} %", file=file)
    if s.get("mode") in ("lockstep", "realtime"):
        line = f"  {s['mode']} over {s['bus']}: round trip p50 {_fmt(s.get('round_trip_p50_us'), '.0f')} us"
        if s["mode"] == "realtime":
            late, away = s.get("missed_deadlines_plant_started_late"), s.get("missed_deadlines_cpu_away")
            why = ([f"{late} in periods the plant itself began past the deadline: a stall of its process or CPU"]
                   if late else []) + ([f"{away} with a CPU taken away by the machine"] if away else [])
            line += (f", missed deadlines {s.get('missed_deadlines')}" + (f" ({'; '.join(why)})" if why else "")
                     + f", jitter p99 {_fmt(s.get('jitter_p99_us'), '.0f')} us")
        bad, bad_tcu = sum((s.get("rejected_frames") or {}).values()), sum((s.get("tcu_rejected_frames") or {}).values())
        if bad or bad_tcu:
            line += f"; rejected frames: plant {bad}, TCU {bad_tcu}"
        print(line, file=file)
    if s.get("unmapped_ids"):
        print("  frames of ids the mapping does not name (not acted on): "
              + ", ".join(f"{k} x{n}" for k, n in s["unmapped_ids"].items()), file=file)
    outside = {k: n for k, n in (s.get("out_of_range_signals") or {}).items() if n}
    if outside:
        print("  signals outside their DBC range: " + ", ".join(f"{k} x{n}" for k, n in outside.items()), file=file)
    if s.get("suspicious"):
        print("  suspicious frames (another node on the bus?): "
              + ", ".join(f"{k} x{n}" for k, n in sorted(s["suspicious"].items())), file=file)
    if s.get("mcap"):
        print(f"  log: {s['mcap']}", file=file)
