"""``hil bench identify``: every strategy on the same measured samples, judged against the truth.

Two modes.  ``--family NAME --draws K [--seed S]``: K fault curves drawn from a documented family
(``plant.families``; the draws' seed chosen at run time unless given, and printed), one plant run per
draw, every strategy fed its readings and judged by ``hil.benchmarks.judge`` (correct confirmations,
wrong ones, interval coverage, RT).  ``--cases`` (FFCC-a/b and any scenario files, seeds 1..N): the
paper's Table 3 (MSE, RMSE, MAE, R², RT, corrections) plus the same verdicts per seed, peak errors and
the identifier's cost per sample.

Per case and seed the plant, the sensors and the TCU's torque demand run once; the sensor readings
are recorded and then replayed, reading by reading, into a fresh ``TractionIdentifier`` per
strategy, so every strategy sees the identical data.  Each ``on_sensor`` call of the identifying
phase (slip detected -> confirmed or end of run) is timed: that is the cost per sample.  A run
feeds at most a few hundred samples (docs/design/benchmarks.md has the counts), so a seed's p99 is
set by its few costliest samples (a window's end, the spread prelim's polish or the filter's
opening); the table's p99 is the median over seeds of that, the worst seed's beside it.  Readings
are fed with the garbage collector frozen and disabled, as the TCU process runs in real time; the
readings before the strategy's first sample (monitoring, where the drill of identifier/drill.py
keeps the strategy's code warm) are timed too.
Seeds 1..N are for reporting; tune on others (``--first-seed``).  Beside each strategy's curve the
bench reports what its samples alone determine (``data_limit``: the NLLS baseline's fit to them
from the true curve), so an accuracy figure shows how much of it comes from the data and how much from the prior.

Observer-aware strategies (``*_oa``, identifier/strategies/observer_aware.py) fit the observer's
predicted output mu^_pred(theta) rather than M(v_s; theta): their ``r2`` is still the paper's (the
static curve against the raw mu^ samples, which they take from the slip detection on, through the
observer's transient), and ``r2_observer_model`` is mu^ against mu^_pred(theta).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .. import terminal
from .judge import TOL_PEAK_CREEP_PERCENT, TOL_PEAK_MU_PERCENT, judge
from .judge import quantile_or_inf as judge_quantile
from .judge import aggregate as judge_aggregate
from .judge import table as judge_table
from .judge import unconfirmed_fraction
from ..exchange import collector_paused
from ..progress import Progress
from ..sweep.engine import map_in_order
from ..config import load_scenario
from ..trace import clean, summarise
from ..trace import fmt as _f

MEDIAN_KEYS = ("rt_percent", "mse", "rmse", "mae", "r2", "r2_true_curve", "r2_vs_truth", "r2_vs_truth_to_peak",
               "r2_observer_model",
               "r2_true_curve_observer_model", "peak_mu_err_percent",
               "peak_creep_err_percent", "corrections", "samples", "t_det_s", "curve_rmse_vs_truth",
               "lsq_truth_r2_vs_truth", "lsq_truth_peak_mu_err_percent", "lsq_truth_peak_creep_err_percent")


def register(sub) -> None:
    from identifier import STRATEGIES

    p = sub.add_parser("identify", help="all strategies on the same measured samples: Table 3 of the paper, "
                       "peak errors, verdict and cost per sample")
    p.add_argument("--family", default=None, help="draw the fault curves from this family (exp, polach, default: "
                   "plant/families.py) instead of --cases")
    p.add_argument("--draws", type=int, default=200, help="with --family: how many curves (default 200)")
    p.add_argument("--seed", type=int, default=None, help="with --family: the draws' seed (default: drawn now and "
                   "printed)")
    p.add_argument("--base", default="ffcc_a", help="with --family: the scenario whose vehicle, NFCC-0, sensors and "
                   "TCU settings every draw keeps (default ffcc_a)")
    p.add_argument("--wide", action="store_true", help="with --family: every column aligned, not only those a "
                   "reader decides on")
    p.add_argument("--markdown", action="store_true", help="every column: with --cases the full table (Table 3, "
                   "verdicts, costs) and its notes, with --family the whole report, as markdown")
    p.add_argument("--report", metavar="DIR", default=None, help="with --family: also write DIR/identification.md "
                   "(the markdown report) and DIR/identification.json (what --json prints)")
    p.add_argument("--oracle-draws", type=int, default=None, help="curves the offline oracle draws from the family "
                   "per run (hil/benchmarks/oracle.py; default 4000 with --family, 0 otherwise; 0: no oracle)")
    p.add_argument("--oracle-family", default="exp", help="with --cases: the family whose prior the oracle knows "
                   "(default exp, the paper's form)")
    p.add_argument("--cases", default="ffcc_a,ffcc_b", help="scenario names (scenarios/NAME.toml) or TOML paths")
    p.add_argument("--strategies", default=",".join(STRATEGIES), help="comma-separated (default: all)")
    p.add_argument("--seeds", type=int, default=20, help="seeds 1..N (default 20)")
    p.add_argument("--first-seed", type=int, default=1, help="first seed (default 1: seeds 1..N are for reporting; "
                   "tune on others, e.g. --first-seed 100)")
    p.add_argument("--particles", type=int, default=None, help="particles N for the particle-filter strategies")
    p.add_argument("--set", action="append", metavar="TABLE.KEY=VALUE",
                   help="override a scenario field for every case, e.g. --set identifier.settle_time_s=0.006")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--plots", metavar="DIR", default=None, help="write PNG figures (first seed) to DIR")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None, help="run the draws (--family) or the case seeds "
                   "on this Dask cluster (tcp://HOST:PORT; hil sweep's engine); the same verdicts as the serial run")
    p.add_argument("--workers", type=int, default=None, help="run the draws or case seeds on a local Dask cluster "
                   "of this many worker processes (default: serially in this process); costs are then timed "
                   "with the workers side by side")
    p.set_defaults(func=cmd_identify)


def case_path(name: str) -> Path:
    """A TOML path as given, else scenarios/NAME.toml (in the working directory, else the repository's)."""
    p = Path(name)
    if p.suffix == ".toml":
        return p
    local = Path("scenarios") / f"{name}.toml"
    return local if local.exists() else Path(__file__).resolve().parents[2] / "scenarios" / f"{name}.toml"


# -- data: one plant run per case and seed ------------------------------------------------------
@dataclasses.dataclass
class CaseData:
    scenario: object
    seed: int
    readings: list
    tracker: object
    plant_torques_nm: list = dataclasses.field(default_factory=list)    # the command after each reading


def generate(scenario, seed: int) -> CaseData:
    """Run plant + sensors with the TCU's torque demand and record the sensor readings."""
    from identifier import TorqueCommand
    from identifier.excitation import Excitation
    from identifier.tcu import SlipDetector, creep_speed_kmh

    from ..plant_node import PlantRig
    from ..trace import Trace

    trace = Trace(scenario)
    rig = PlantRig(scenario, seed, trace)
    settings = scenario.identifier_settings()
    excitation = Excitation.from_dict(settings.excitation)
    # the TCU's own slip detector and excitation (identifier/tcu.py), so the plant gets the commands
    # every strategy's TCU would send: they depend on the readings and the seed, never on a strategy
    detector = SlipDetector(settings.detection_creep_rise_kmh, settings.baseline_samples)
    readings, torques = [], []
    for _ in range(scenario.steps):
        r = rig.sense()
        readings.append(r)
        if excitation.active and math.isfinite(r.motor_speed_rad_s) and math.isfinite(r.train_speed_ms):
            detector.update(r.step, creep_speed_kmh(r, settings.vehicle))
        torque = excitation.command_nm(settings.torque_demand_nm, r.step, detector.detected_step, settings.period_s,
                                       seed)
        rig.apply(TorqueCommand(r.step, torque))
        torques.append(torque)
    return CaseData(scenario, seed, readings, trace.tracker, torques)


def with_particles(settings, strategy: str, particles: int | None):
    if particles is None:
        return settings
    from identifier import STRATEGIES
    from identifier.strategies.mdipf import MdipfStrategy

    if not issubclass(STRATEGIES[strategy], MdipfStrategy):
        return settings
    options = {k: dict(v) if isinstance(v, dict) else v for k, v in settings.options.items()}
    options.setdefault(strategy, {})["particles"] = particles
    return dataclasses.replace(settings, options=options)


#: monitoring readings left out of its cost: the first ones, while the identifier's objects are new
_MONITORING_SKIP = 20


def _feed(ident, readings, events, costs_ns, quiet_ns, monitoring_ns) -> None:
    """The readings into ``ident`` until it confirms or gives up, each ``on_sensor`` call timed."""
    clock = time.perf_counter_ns
    fed = 0
    for r in readings:
        t0 = clock()
        out = ident.on_sensor(r)
        dt = clock() - t0
        events.extend(out.events)
        if ident.strategy.samples > fed or out.events:     # this reading reached the strategy
            fed = ident.strategy.samples
            costs_ns.append(dt)
            if not out.events:
                quiet_ns.append(dt)     # a filter step alone, no window end
        elif not fed:
            monitoring_ns.append(dt)    # before the strategy's first sample: observer, detector, drill
        if ident.strategy.confirmed or ident.strategy.gave_up:
            break


def replay(data: CaseData, strategy: str, particles: int | None) -> tuple[dict, object]:
    """Feed the recorded readings to a fresh identifier; summary (hil run --json keys) + costs."""
    from identifier import TractionIdentifier

    sc = data.scenario
    try:
        settings = with_particles(sc.identifier_settings(), strategy, particles)
        ident = TractionIdentifier(settings, strategy, data.seed)
    except ValueError as e:
        raise ConfigError(f"{sc.path}: [identifier] options for {strategy}: {e}") from None
    events, costs_ns, quiet_ns, monitoring_ns = [], [], [], []
    with collector_paused():        # as the TCU process runs in real time (hil/tcu_node.py)
        _feed(ident, data.readings, events, costs_ns, quiet_ns, monitoring_ns)
    ident.events_seen = events
    v, mu = ident.strategy.data()
    detected = ident.detector.detected_step
    period = sc.run.exchange_period_s
    s = summarise(scenario=sc, strategy=strategy, seed=data.seed, bus="replay", tracker=data.tracker, events=events,
                  samples_v=v, samples_mu=mu, t_detected_s=None if detected is None else detected * period,
                  mcap_path=None)
    from identifier.metrics import fit_metrics

    # the figures that need the true curve in the identifier's own form (exp); None for other laws
    true_theta = np.asarray(sc.fault_curve.params) if hasattr(sc.fault_curve, "params") else None
    s["r2_true_curve"] = clean(fit_metrics(v, mu, true_theta)["r2"]) if len(v) and true_theta is not None else None
    # observer-aware strategies fit mu^_pred(theta) (the observer's predicted output), not M(v_s; theta):
    # their R² against that model, for the identified and for the true curve (the paper's r2 stays as is)
    s["r2_observer_model"] = s["r2_true_curve_observer_model"] = None
    if hasattr(ident.strategy, "observer_model_metrics") and len(v):
        if s.get("params") is not None:
            s["r2_observer_model"] = clean(ident.strategy.observer_model_metrics(np.asarray(s["params"]))["r2_observer_model"])
        if true_theta is not None:
            s["r2_true_curve_observer_model"] = clean(
                ident.strategy.observer_model_metrics(true_theta)["r2_observer_model"])
    c = np.asarray(costs_ns, float) / 1e3
    s["cost_median_us"] = float(np.median(c)) if c.size else None
    s["cost_p99_us"] = float(np.percentile(c, 99)) if c.size else None
    s["cost_max_us"] = float(c.max()) if c.size else None
    q = np.asarray(quiet_ns, float) / 1e3
    s["cost_p99_between_windows_us"] = float(np.percentile(q, 99)) if q.size else None
    s["cost_samples"] = int(c.size)
    # the readings before the strategy's first sample (monitoring and the settle time, where the
    # drill runs): their cost is the TCU's too, so it is reported beside the identifying phase's
    m = np.asarray(monitoring_ns[_MONITORING_SKIP:], float) / 1e3
    s["cost_monitoring_median_us"] = float(np.median(m)) if m.size else None
    s["cost_monitoring_p99_us"] = float(np.percentile(m, 99)) if m.size else None
    s["drill_cycles"] = None if ident.drill is None else ident.drill.cycles
    s["drill_error"] = None if ident.drill is None else ident.drill.error
    s["cost_p99_percent_of_period"] = None if not c.size else s["cost_p99_us"] / (period * 1e6) * 100.0
    v_true, mu_true = sc.fault_curve.peak()
    s.update(judge(s, events, mu_true, v_true, data.tracker.serious_time_s))
    s.update(data_limit(v, mu, true_theta, getattr(ident.strategy, "observer_aware", False)))
    return s, ident


def data_limit(creep_speed_kmh, mu_samples, true_theta, observer_aware: bool = False) -> dict:
    """What the strategy's samples alone say about the curve: the NLLS baseline's fit of M(v_s; theta)
    to them (``nlls.fit_curve``: within the physical bounds, no prior, no box, no window), started at
    the *true* curve so that no search can miss the samples' own optimum near it.  Its R² vs truth
    and peak errors are what the data determine; a strategy that does better does so by its prior
    (initial guess, box, particle spread), not by the data.  None for observer-aware strategies
    (their samples include the observer's transient, which M(v_s; theta) does not model) and for
    fewer samples than parameters."""
    from identifier.curve import peak
    from identifier.metrics import peak_errors, r2_vs_truth
    from identifier.strategies.nlls import fit_curve

    keys = ("lsq_truth_r2_vs_truth", "lsq_truth_peak_mu_err_percent", "lsq_truth_peak_creep_err_percent")
    out = dict.fromkeys(keys)
    out["lsq_truth_ok_peaks"] = out["lsq_truth_params"] = None
    if true_theta is None:          # a true curve of another law (e.g. Polach): no exp-form start
        return out
    v, mu = np.asarray(creep_speed_kmh, float), np.asarray(mu_samples, float)
    ok = np.isfinite(v) & np.isfinite(mu)
    v, mu = v[ok], mu[ok]
    true_theta = np.asarray(true_theta, float)
    if observer_aware or v.size < true_theta.size:
        return out
    with np.errstate(over="ignore", invalid="ignore"):     # the solver may try steep exponents on its way
        theta = fit_curve(v, mu, true_theta)
    pe = peak_errors(theta, true_theta)
    out.update(lsq_truth_r2_vs_truth=clean(r2_vs_truth(theta, true_theta, 2.0 * peak(true_theta)[0])),
               lsq_truth_peak_mu_err_percent=clean(pe["peak_mu_err_percent"]),
               lsq_truth_peak_creep_err_percent=clean(pe["peak_creep_err_percent"]),
               lsq_truth_params=[float(x) for x in theta])
    out["lsq_truth_ok_peaks"] = bool(pe["peak_mu_err_percent"] <= TOL_PEAK_MU_PERCENT
                                     and pe["peak_creep_err_percent"] <= TOL_PEAK_CREEP_PERCENT)
    return out


def form_limit(fault_curve, creep_max_kmh: float) -> dict:
    """What the identifier's curve form can say at best over the creep range its samples covered:
    the paper's two-term form (written by peak mu, peak creep, mu(0) and two shapes,
    identifier/prior.py), least-squares fitted to the *noiseless* true curve at 200 creeps on
    [0, ``creep_max_kmh``], from a few shapes started at the true peak, bounded by a box wider than
    any prior's.  Its peak errors are the form's floor on that range: for a true curve of the same
    form about zero; for another law (Polach) a confirmation can be wrong by this much with no noise
    at all, so a wrong confirmation there is the form's, not the noise's.  ``form_ok``: both peak
    errors within the tolerance."""
    from scipy.optimize import least_squares

    from identifier.prior import theta_from_phi

    out = {"form_peak_mu_err_percent": None, "form_peak_creep_err_percent": None, "form_ok": None}
    v_true, mu_true = fault_curve.peak()
    if not (math.isfinite(creep_max_kmh) and creep_max_kmh > 0):
        return out
    v = np.linspace(0.0, creep_max_kmh, 200)
    target = np.asarray(fault_curve.mu(v), float)
    lo, hi = [0.01, 0.05, 0.0, 0.05, 1.01], [1.0, 20.0, 0.2, 10.0, 20.0]

    def residual(phi):
        l0, l1, l2, t1, t2 = theta_from_phi(phi)
        return l0 + l1 * np.exp(t1 * v) + l2 * np.exp(t2 * v) - target

    best = None
    for a in (0.5, 1.0, 2.0):
        for r in (1.5, 3.0):
            start = np.clip([mu_true, v_true, min(float(target[0]), 0.15), a, r], lo, hi)
            with np.errstate(over="ignore", invalid="ignore"):
                fit = least_squares(residual, start, bounds=(lo, hi), x_scale="jac")
            if best is None or fit.cost < best.cost:
                best = fit
    mu_err = abs(best.x[0] - mu_true) / mu_true * 100.0
    creep_err = abs(best.x[1] - v_true) / v_true * 100.0
    out.update(form_peak_mu_err_percent=float(mu_err), form_peak_creep_err_percent=float(creep_err),
               form_ok=bool(mu_err <= TOL_PEAK_MU_PERCENT and creep_err <= TOL_PEAK_CREEP_PERCENT))
    return out


def _median(values):
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(np.median(vals)) if vals else None


def aggregate(per_seed: list[dict]) -> dict:
    """Medians over seeds (RT over identified seeds only), 'identified' as a fraction, and the
    verdicts of ``judge.aggregate`` (correct, wrong confirmations, coverage ...)."""
    out = {k: _median([s.get(k) for s in per_seed]) for k in MEDIAN_KEYS}
    out["identified"] = float(np.mean([s["identified"] for s in per_seed]))
    out.update(judge_aggregate(per_seed))
    limits = [s["lsq_truth_ok_peaks"] for s in per_seed if s.get("lsq_truth_ok_peaks") is not None]
    out["lsq_truth_ok_peaks"] = float(np.mean(limits)) if limits else None
    costs = [s for s in per_seed if s["cost_p99_us"] is not None]
    out["cost_median_us"] = _median([s["cost_median_us"] for s in costs])
    # per-seed p99s, then their median (one busy moment on a shared machine does not set the figure);
    # the worst seed's p99 is kept beside it
    out["cost_p99_us"] = _median([s["cost_p99_us"] for s in costs])
    out["cost_p99_percent_of_period"] = _median([s["cost_p99_percent_of_period"] for s in costs])
    out["cost_p99_worst_us"] = float(np.max([s["cost_p99_us"] for s in costs])) if costs else None
    out["cost_p99_between_windows_us"] = _median([s["cost_p99_between_windows_us"] for s in per_seed])
    out["cost_monitoring_median_us"] = _median([s["cost_monitoring_median_us"] for s in per_seed])
    out["cost_monitoring_p99_us"] = _median([s["cost_monitoring_p99_us"] for s in per_seed])
    errors = sorted({s["drill_error"] for s in per_seed if s.get("drill_error")})
    out["drill_errors"] = errors
    out["seeds"] = per_seed
    return out


# -- output ----------------------------------------------------------------------------------
def _obs(r) -> str:
    if r.get("r2_observer_model") is None:
        return "-"
    return f"{_f(r['r2_observer_model'], '.5f')} ({_f(r['r2_true_curve_observer_model'], '.5f')})"


def _pct(x) -> str:
    return "n/a" if x is None else f"{x * 100:.0f}%"


def _limit(r) -> str:
    if r.get("lsq_truth_ok_peaks") is None:
        return "-"
    return f"{r['lsq_truth_ok_peaks'] * 100:.0f}%, {_f(r['lsq_truth_r2_vs_truth'], '.3f')}"


def terminal_table(results: dict, cases: list[str], n_seeds: int) -> str:
    """The columns a reader decides on, within ``terminal.WIDTH``: verdicts, RT, peak mu error, coverage."""
    head = ["strategy", "case", "correct", "wrong", "unconfirmed", "RT %", "peak μ err %", "covers μ / creep"]
    rows = []
    for strat, per_case in results.items():
        for case in cases:
            r = per_case[case]
            rows.append([strat, case, _pct(r["correct_fraction"]), _pct(r["wrong_confirmation_fraction"]),
                         _pct(unconfirmed_fraction(r)), _f(r["rt_percent"], ".1f"), _f(r["peak_mu_err_percent"], ".2f"),
                         f"{_pct(r['coverage_peak_mu'])} / {_pct(r['coverage_peak_creep'])}"])
    notes = terminal.wrap(
        f"Medians over {n_seeds} seeds. correct: confirmed with peak μ err <= {TOL_PEAK_MU_PERCENT:g} % and peak "
        f"creep err <= {TOL_PEAK_CREEP_PERCENT:g} % of the true curve's; wrong: confirmed otherwise; covers: the "
        "strategy's 90 % intervals hold the true peak (an open one never does). Every column (Table 3, costs) "
        "and the notes: --markdown; every figure: --json.")
    return terminal.columns(head, rows) + "\n\n" + notes


def table(results: dict, cases: list[str], n_seeds: int) -> str:
    """The paper's Table 3 with the verdicts, peak errors and costs: every column, as markdown."""
    head = ("| strategy | case | MSE | RMSE | MAE | R² | R² true curve | R² obs. model (true) | R² vs truth | RT % | corrections | peak μ err % | "
            "peak creep err % | identified | correct | wrong confirmations | 90 % CI covers peak μ / creep | cost median µs | cost p99 µs | p99 % of period | "
            "p99 between windows µs | monitoring cost median / p99 µs | the samples' LS from truth: ok peaks, R² vs truth |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for strat, per_case in results.items():
        for case in cases:
            r = per_case[case]
            lines.append(
                f"| {strat} | {case} | {_f(r['mse'], '.3e')} | {_f(r['rmse'], '.3e')} | {_f(r['mae'], '.3e')} | "
                f"{_f(r['r2'], '.5f')} | {_f(r['r2_true_curve'], '.5f')} | {_obs(r)} | {_f(r['r2_vs_truth'], '.5f')} | "
                f"{_f(r['rt_percent'], '.1f')} | "
                f"{_f(r['corrections'], '.0f')} | {_f(r['peak_mu_err_percent'], '.2f')} | "
                f"{_f(r['peak_creep_err_percent'], '.2f')} | {r['identified'] * 100:.0f}% | {_pct(r['correct_fraction'])} | "
                f"{_pct(r['wrong_confirmation_fraction'])} | {_pct(r['coverage_peak_mu'])} / {_pct(r['coverage_peak_creep'])} | "
                f"{_f(r['cost_median_us'], '.1f')} | {_f(r['cost_p99_us'], '.1f')} | "
                f"{_f(r['cost_p99_percent_of_period'], '.1f')} | {_f(r['cost_p99_between_windows_us'], '.1f')} | "
                f"{_f(r['cost_monitoring_median_us'], '.1f')} / {_f(r['cost_monitoring_p99_us'], '.1f')} | {_limit(r)} |")
    notes = (f"\nMedians over {n_seeds} seeds (RT, fit and peak errors over the seeds' final curves; cost p99 is the "
             f"median over seeds of each seed's p99). R²: the paper's, of the identified curve against the μ̂ samples. "
             "R² true curve: the true fault curve against the same μ̂ samples (the R² the samples allow). "
             "R² vs truth: the identified curve against the true curve on 200 points over [0, 2 × the true peak creep]. "
             f"correct = confirmed with peak μ err <= {TOL_PEAK_MU_PERCENT:g} % and peak creep err <= "
             f"{TOL_PEAK_CREEP_PERCENT:g} % of the true curve's, as % of seeds; wrong confirmations: confirmed but not "
             "correct; 90 % CI covers: the strategy's own intervals at confirmation (else the last before the serious "
             "stage) hold the true peak, as % of the seeds where it published any (an open interval, its upper end the "
             "strategy's range and not the data's, never does). R² obs. model: observer-aware strategies only (*_oa), R² of μ̂ against the "
             "observer's predicted output μ̂_pred(θ) for the identified θ (and, in brackets, for the true curve). Cost: wall time of TractionIdentifier.on_sensor per reading that fed a "
             "sample to the strategy (median; p99, also as % of the sampling period); 'p99 between windows' leaves "
             "out the readings that closed a window (the NLLS fits and the corrections). Monitoring cost: the same "
             "per reading before the strategy's first sample (observer, slip detector and, for the particle "
             "strategies, the drill that keeps their code warm: identifier/drill.py; "
             "--set identifier.drill_particles=0 turns it off). The samples' LS from truth: the NLLS baseline's fit of "
             "M(v_s; θ) (physical bounds) to the strategy's own samples at its confirmation, started at the true curve, with no prior "
             "(what the data determine; a strategy above it owes the difference to its prior; - for *_oa).\n")
    return "\n".join(lines) + notes


def cmd_identify(args) -> int:
    from identifier import STRATEGIES

    from ..config import parse_set

    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    for s in strategies:
        if s not in STRATEGIES:
            raise ConfigError(f"--strategies: unknown strategy {s!r}; available: {', '.join(sorted(STRATEGIES))}")
    if args.seeds < 1:
        raise ConfigError("--seeds: must be >= 1")
    if args.particles is not None and args.particles < 2:
        raise ConfigError("--particles: must be >= 2")
    overrides = parse_set(args.set)
    if args.family is not None:
        return cmd_family(args, strategies, overrides)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    scenarios = {}
    for c in cases:
        path = case_path(c)
        if not path.exists():
            raise ConfigError(f"--cases: no scenario file {path}")
        scenarios[c] = load_scenario(path, overrides)
    if args.first_seed < 0:
        raise ConfigError("--first-seed: must be >= 0")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    per_seed = {s: {c: [] for c in cases} for s in strategies}
    first_runs = {c: {} for c in cases}
    oracle_rts = {c: [] for c in cases}
    if args.oracle_draws:
        from plant import families
        if args.oracle_family not in families.FAMILIES:
            raise ConfigError(f"--oracle-family {args.oracle_family!r}: unknown family (known: "
                              f"{', '.join(families.FAMILIES)})")
    bar = Progress(len(cases) * len(seeds) * (len(strategies) + 1), "bench identify", None)
    keys = [(c, seed) for c in cases for seed in seeds]
    jobs = [(scenarios[c], seed, strategies, args.particles, args.oracle_family, args.oracle_draws) for c, seed in keys]
    # one (case, seed) per call, serially here or on Dask (--scheduler / --workers): the same summaries
    outs = map_in_order(case_seed, jobs, args.scheduler, args.workers,
                        lambda n, i: bar.update(n * (len(strategies) + 1), f"{keys[i][0]} seed {keys[i][1]}"))
    for (c, seed), out in zip(keys, outs):
        for strat in strategies:
            per_seed[strat][c].append(out["summaries"][strat])
        if out["oracle"] is not None:
            oracle_rts[c].append(out["oracle"]["oracle_rt_percent"])
            for strat in strategies:
                per_seed[strat][c][-1]["oracle_rt_percent"] = out["oracle"]["oracle_rt_percent"]
    if args.plots:          # the first seed's runs again, here: the figures need the identifiers themselves
        for c in cases:
            data = generate(scenarios[c], seeds[0])
            for strat in strategies:
                summary, ident = replay(data, strat, args.particles)
                first_runs[c][strat] = (summary, ident, data)
    bar.close()
    results = {s: {c: aggregate(per_seed[s][c]) for c in cases} for s in strategies}
    for per_case in results.values():
        for c, r in per_case.items():
            r["oracle_rt_median_percent"] = judge_quantile(oracle_rts[c], 50) if oracle_rts[c] else None
    for s, per_case in results.items():
        for c, r in per_case.items():
            for e in r["drill_errors"]:     # the drill never stops a run, but a stopped drill is news
                print(f"bench identify: warning: {s} on {c}: the drill stopped: {e}", file=sys.stderr)
    if args.plots:
        paths = write_plots(Path(args.plots), first_runs, strategies)
        print(f"wrote {len(paths)} figures to {args.plots}", file=sys.stderr)
    if args.json:
        print(json.dumps(clean({"recommended": recommended(), "results": results})))
    else:
        print(table(results, cases, len(seeds)) if args.markdown else terminal_table(results, cases, len(seeds)))
    return 0


def case_seed(job) -> dict:
    """One seed of one ``--cases`` scenario: its plant run, every strategy fed and summarised, the
    oracle.  Plain data in and out, so it runs on a Dask worker as well as here."""
    scenario, seed, strategies, particles, oracle_family, oracle_draws = job
    data = generate(scenario, seed)
    summaries = {strat: replay(data, strat, particles)[0] for strat in strategies}
    oracle = run_oracle(data, oracle_family, [seed, 1], oracle_draws) if oracle_draws else None
    return {"summaries": summaries, "oracle": oracle}


def run_oracle(data: CaseData, family: str, seed, draws: int) -> dict:
    """The information limit on this run's samples (hil/benchmarks/oracle.py): every sample the
    ``bayes`` strategy would receive from the slip's start until the creep passes its prior's highest
    peak creep (a copy of it that never confirms collects them; its filter settings are the oracle's)."""
    from .oracle import oracle, oracle_rt_percent

    from identifier import TractionIdentifier

    options = {"tol_peak_mu": 1e-12, "particles": 10, "compiled": False}
    sc = data.scenario
    sc_settings = sc.identifier_settings()
    opts = {k: dict(v) if isinstance(v, dict) else v for k, v in sc_settings.options.items()}
    opts["bayes"] = {**opts.get("bayes", {}), **options}
    ident = TractionIdentifier(dataclasses.replace(sc_settings, options=opts), "bayes", data.seed)
    for r in data.readings:
        ident.on_sensor(r)
        if ident.strategy.gave_up:
            break
    o = oracle(ident.strategy, family, seed, draws)
    t_det = None if data.tracker.serious_time_s is None else data.tracker.serious_time_s - sc.run.fault_time_s
    o["oracle_rt_percent"] = oracle_rt_percent(o, sc.run.fault_time_s, t_det)
    return o


def recommended() -> str:
    """The default (recommended) strategy (``identifier.strategies.DEFAULT_STRATEGY``)."""
    from identifier import strategies

    return strategies.DEFAULT_STRATEGY


def cmd_family(args, strategies: list[str], overrides: dict) -> int:
    """``--family NAME --draws K [--seed S]``: K draws, every strategy judged on each (module docstring)."""
    import secrets

    from plant import families

    if args.family not in families.FAMILIES:
        raise ConfigError(f"--family {args.family!r}: unknown family (known: {', '.join(families.FAMILIES)})")
    if args.draws < 1:
        raise ConfigError("--draws: must be >= 1")
    seed = secrets.randbits(31) if args.seed is None else args.seed
    if seed < 0:
        raise ConfigError("--seed: must be >= 0")
    base = case_path(args.base)
    if not base.exists():
        raise ConfigError(f"--base: no scenario file {base}")
    print(f"bench identify: family {args.family}, {args.draws} draws, seed {seed} (repeat them with --family "
          f"{args.family} --draws {args.draws} --seed {seed})", file=sys.stderr)
    per_draw = {s: [] for s in strategies}
    costs = {s: [] for s in strategies}
    bar = Progress(args.draws * (len(strategies) + 1), f"bench identify {args.family}", None)
    from .oracle import DRAWS as ORACLE_DRAWS

    oracle_draws = ORACLE_DRAWS if args.oracle_draws is None else args.oracle_draws
    load_before = os.getloadavg()
    oracle_rts, oracle_detail = [], []
    base_text = base.read_text()
    jobs = [(base_text, args.family, seed, i, overrides, strategies, args.particles, oracle_draws)
            for i in range(args.draws)]
    # one draw per call, serially here or on Dask (--scheduler / --workers): the same verdicts either way
    for out in map_in_order(family_draw, jobs, args.scheduler, args.workers,
                            lambda n, i: bar.update(n * (len(strategies) + 1), f"draw {i}")):
        for strat in strategies:
            per_draw[strat].append(out["verdicts"][strat])
            costs[strat].append(out["costs"][strat])
        if out["oracle"] is not None:
            oracle_rts.append(out["oracle"]["oracle_rt_percent"])
            oracle_detail.append(out["oracle"])
    bar.close()
    results = {}
    oracle_median = judge_quantile(oracle_rts, 50) if oracle_rts else None
    for strat in strategies:
        r = judge_aggregate(per_draw[strat])
        r["cost_p99_us"] = _median(costs[strat])
        r["oracle_rt_median_percent"] = oracle_median
        r["rt_median_over_oracle"] = (r["rt_median_percent"] / oracle_median
                                      if oracle_median and math.isfinite(oracle_median) else None)
        r["draws_detail"] = per_draw[strat]
        results[strat] = r
    family = {"name": args.family, "draws": args.draws, "spec": families.describe(args.family)}
    oracle_summary = {"draws_per_run": oracle_draws, "rt_median_percent": oracle_median,
                      "rt_p90_percent": judge_quantile(oracle_rts, 90) if oracle_rts else None,
                      "runs": oracle_detail}
    document = {"family": family, "seed": seed, "recommended": recommended(), "results": results,
                "oracle": oracle_summary}
    if args.report:
        out = Path(args.report)
        out.mkdir(parents=True, exist_ok=True)
        (out / "identification.json").write_text(json.dumps(clean(document)) + "\n")
        (out / "identification.md").write_text(family_markdown(args, seed, results, oracle_summary, load_before))
        print(f"bench identify: wrote {out / 'identification.md'} and {out / 'identification.json'}", file=sys.stderr)
    if args.json:
        print(json.dumps(clean(document)))
    else:
        if args.markdown:
            print(family_markdown(args, seed, results, oracle_summary, load_before))
        else:
            print(f"family {args.family}: {args.draws} draws, seed {seed}; recommended strategy: {recommended()}")
            print(judge_table(results, args.wide, args.markdown))
            print(terminal.wrap(f"oracle (the family's exact prior, hil/benchmarks/oracle.py): RT median "
                                f"{_f(oracle_median, '.1f')} %, p90 {_f(oracle_summary['rt_p90_percent'], '.1f')} %; "
                                f"before the serious stage in {_pct(_fraction_below(oracle_rts, 100.0))} of draws"))
    return 0


def family_draw(job) -> dict:
    """Draw ``i`` of ``--family``: its plant run, every strategy fed and judged, the oracle.  Plain data in
    and out, so it runs on a Dask worker as well as here (``hil.sweep.engine.map_in_order``)."""
    from plant import families

    from ..config import parse_scenario

    base_text, family, seed, i, overrides, strategies, particles, oracle_draws = job
    text = families.draw_scenario_text(base_text, family, seed, i)
    sc = parse_scenario(text, f"{family} draw {i} of seed {seed}", overrides)
    data = generate(sc, i + 1)
    v_true, mu_true = sc.fault_curve.peak()
    law = getattr(sc.fault_curve, "model", type(sc.fault_curve).__name__)
    verdicts, costs = {}, {}
    for strat in strategies:
        summary, ident = replay(data, strat, particles)
        d = judge(summary, ident.events_seen, mu_true, v_true, data.tracker.serious_time_s)
        d.update(draw=i, t_det_s=summary["t_det_s"], peak_mu_ci=summary.get("peak_mu_ci"),
                 peak_creep_ci=summary.get("peak_creep_ci"), law=law)
        if d["confirmed"]:      # the form's own floor over the creeps it had seen (form_limit)
            v_seen = [x for x in ident.strategy.data()[0] if math.isfinite(x)]
            d.update(form_limit(sc.fault_curve, max(v_seen) if v_seen else math.nan))
        verdicts[strat] = d
        costs[strat] = summary.get("cost_p99_us")
    oracle_out = None
    if oracle_draws:
        oracle_out = run_oracle(data, family, [seed, i], oracle_draws)
        oracle_out.update(draw=i, true_peak_mu=mu_true, true_peak_creep_kmh=v_true)
    return {"verdicts": verdicts, "costs": costs, "oracle": oracle_out}


def _fraction_below(values, limit: float):
    vals = [v for v in values if v is not None]
    return sum(v < limit for v in vals) / len(vals) if vals else None


def law_lines(results: dict) -> list[str]:
    """Per law of the true curve: wrong confirmations and coverage, and the form limit's count."""
    lines = ["## By law of the true curve, and the form limit", "",
             "Wrong confirmations and 90 % coverage per law; *form cannot*: of the wrong confirmations, how many "
             "are on draws where the identifier's own two-term form, least-squares fitted to the noiseless true "
             "curve over the creeps the strategy had seen (hil/benchmarks/identify.py `form_limit`), misses the "
             "tolerance too: a form error, not a noise error.", "",
             "| strategy | law | draws | correct | wrong | covers peak μ | … peak creep |", "|---|---|---|---|---|---|---|"]
    for strat, r in results.items():
        for law, x in (r.get("by_law") or {}).items():
            lines.append(f"| {strat} | {law} | {x['draws']} | {_pct(x['correct_fraction'])} | "
                         f"{_pct(x['wrong_confirmation_fraction'])} | {_pct(x['coverage_peak_mu'])} | "
                         f"{_pct(x['coverage_peak_creep'])} |")
    lines.append("")
    for strat, r in results.items():
        if r.get("wrong_confirmations") is not None:
            lines.append(f"- {strat}: {r['wrong_confirmations']} wrong confirmations, of which the form cannot "
                         f"do better on {r['wrong_where_form_cannot']}; its correct confirmations on draws where "
                         f"the form's own fit misses: {r['correct_where_form_cannot']}.")
    return lines


def family_markdown(args, seed: int, results: dict, oracle_summary: dict, load_before) -> str:
    """The whole report of a --family run as a markdown document (what docs/benchmarks/identification.md holds)."""
    import platform

    from plant import families

    rts = [o.get("oracle_rt_percent") for o in oracle_summary["runs"]]
    load_after = os.getloadavg()
    spec = families.describe(args.family)
    lines = [f"# hil bench identify --family {args.family} --draws {args.draws} --seed {seed}", "",
             f"Written by `hil bench identify --family {args.family} --draws {args.draws} --seed {seed} "
             f"--strategies {','.join(results)} --markdown` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
             f"{platform.machine()}, {os.cpu_count()} cores, load average {load_before[0]:.2f} before / "
             f"{load_after[0]:.2f} after.  The draws' seed is drawn at run time unless given (repeat these with --seed {seed}).",
             "", f"Family `{args.family}` (plant/families.py):", "", "```json", json.dumps(spec, indent=1), "```", "",
             f"Recommended strategy: `{recommended()}`.  Verdicts per draw (hil/benchmarks/judge.py): *correct* = "
             f"confirmed with peak mu within {TOL_PEAK_MU_PERCENT:g} % and peak creep within "
             f"{TOL_PEAK_CREEP_PERCENT:g} % of the truth; *wrong* = confirmed otherwise; coverage = the truth inside "
             "the 90 % intervals at the confirmation (else the last published before the serious stage), an open "
             "interval never covering; RT with "
             "unconfirmed draws counted as infinite.", "",
             judge_table(results, True, True), "",
             *law_lines(results), "",
             "## The information limit (oracle)", "",
             f"An offline sequential Monte Carlo posterior over the family's own curves, with the same likelihood "
             f"({oracle_summary['draws_per_run']} curves per run; hil/benchmarks/oracle.py): the first time its 98 % "
             f"intervals are within the tolerance.  RT median {_f(oracle_summary['rt_median_percent'], '.1f')} %, "
             f"p90 {_f(oracle_summary['rt_p90_percent'], '.1f')} %; within tolerance before the serious stage in "
             f"{_pct(_fraction_below(rts, 100.0))} of draws, never in {_pct(sum(r is None or r == math.inf for r in rts) / max(len(rts), 1))}.",
             ""]
    return "\n".join(lines)


# -- figures (paper figs 7-9 / 11-13 and 14-15), first seed -----------------------------------
def write_plots(out_dir: Path, first_runs: dict, strategies: list[str]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from identifier.curve import mu_model
    from identifier.metrics import fit_metrics

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for case, runs in first_runs.items():
        if not runs:
            continue
        _, _, data = next(iter(runs.values()))
        sc = data.scenario
        true_theta = sc.fault_curve.params
        v_peak, _ = sc.fault_curve.peak()
        grid = np.linspace(0.0, 2.5 * v_peak, 300)
        for strat in strategies:
            summary, ident, _ = runs[strat]
            v, mu = ident.strategy.data()
            corr = [e for e in ident_events(summary, ident) if e.kind == "correction"]
            fig, ax = plt.subplots(figsize=(7.5, 4.8))
            ax.plot(v, mu, ".", color="0.55", ms=4, label=f"μ̂ samples ({len(v)})")
            ax.plot(grid, mu_model(grid, true_theta), "k-", lw=2.2, label="true curve")
            cmap = plt.get_cmap("viridis")
            shown = corr if len(corr) <= 8 else corr[:: max(1, len(corr) // 8)] + [corr[-1]]
            for i, e in enumerate(shown):
                ax.plot(grid, mu_model(grid, np.asarray(e.params)), "--", lw=1.1,
                        color=cmap(i / max(1, len(shown) - 1)),
                        label=f"Q={e.correction} ({e.samples} samples, t-t_f={1e3 * (e.t_s - sc.run.fault_time_s):.0f} ms)")
            if hasattr(ident.strategy, "predicted_observer_output") and len(v) and summary.get("params"):
                # observer-aware strategies fit the observer's predicted output, not the curve itself
                ax.plot(v, ident.strategy.predicted_observer_output(np.asarray(summary["params"])), "x-",
                        color="tab:orange", ms=3, lw=0.8, label="μ̂_pred(θ identified): what the strategy fits")
            if summary.get("lsq_truth_params"):
                # what the samples alone say (data_limit): the distance to the true curve is not the strategy's
                ax.plot(grid, mu_model(grid, np.asarray(summary["lsq_truth_params"])), ":", color="0.35", lw=1.2,
                        label="least squares on these samples, from the true curve")
            ax.axvline(v_peak, color="tab:red", lw=1.2, ls=":")
            top = 1.4 * max(sc.fault_curve.peak()[1], 0.05)      # stage labels at the top, clear of the legend
            ax.text(v_peak, 0.94 * top, "  serious stage →", color="tab:red", fontsize=8)
            ax.text(v_peak, 0.94 * top, "← early stage  ", color="tab:red", fontsize=8, ha="right")
            status = (f"confirmed, RT {summary['rt_percent']:.1f} %" if summary["identified"] else "not confirmed")
            ax.set_title(f"{case} {strat} (seed {data.seed}): {status}; peak μ err "
                         f"{_f(summary['peak_mu_err_percent'], '.1f')} %, creep err "
                         f"{_f(summary['peak_creep_err_percent'], '.1f')} %", fontsize=9)
            ax.set_xlabel("creep speed v_s (km/h)")
            ax.set_ylabel("adhesion coefficient μ")
            ax.set_xlim(0, grid[-1])
            ax.set_ylim(0, top)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="lower right")
            fig.tight_layout()
            path = out_dir / f"{case}-{strat}-curves.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            paths.append(path)
        # MSE, RMSE, MAE, R^2 per correction and strategy, against the samples known at that correction
        fig, axes = plt.subplots(2, 2, figsize=(9, 6.2))
        for strat in strategies:
            summary, ident, _ = runs[strat]
            v, mu = ident.strategy.data()
            corr = [e for e in ident_events(summary, ident) if e.kind == "correction"]
            if not corr:
                continue
            m = [fit_metrics(v[:e.samples], mu[:e.samples], np.asarray(e.params)) for e in corr]
            q = [e.correction for e in corr]
            for ax, key in zip(axes.flat, ("mse", "rmse", "mae", "r2")):
                ax.plot(q, [x[key] for x in m], "o-", ms=3, label=strat)
        for ax, key in zip(axes.flat, ("MSE", "RMSE", "MAE", "R²")):
            ax.set_title(key, fontsize=10)
            ax.set_xlabel("correction Q")
            ax.grid(alpha=0.3)
            if key != "R²":
                ax.set_yscale("log")
            else:
                ax.set_ylim(0.9, 1.0005)
        axes.flat[0].legend(fontsize=8)
        fig.suptitle(f"{case}: goodness of fit per correction (seed {data.seed})", fontsize=10)
        fig.tight_layout()
        path = out_dir / f"{case}-metrics.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def ident_events(summary, ident):
    return ident.events_seen
