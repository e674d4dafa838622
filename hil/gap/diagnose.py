"""Sim-to-real gap diagnosis: where the gap lies, which effect explains it, how far it shrinks.

1. The nominal model (the scenario) is driven by the real log's torque commands from the initial
   state measured in the log (straight-line fit over the first 20 ms).  Its mu^ is the TCU's observer
   applied to the model's speeds.  Residual = measured - model on three signals: motor speed, train
   speed (sensor frames) and the TCU's mu^.  Each is divided by its noise floor (the scenario's sensor
   noise and quantum; for mu^ that noise through the observer), so 1 means "as good as the sensors".
2. WHERE: residual RMS per signal, per stage (normal / early / serious, from the measured creep and the
   fault curve's peak creep, and the same for the model), per measured-creep band and per frequency
   band (FFT, against the sensor noise's own share of that band); Ljung-Box whiteness; cross-correlation
   of the residual with the input (torque command) and with the model's creep.
3. WHICH: the run is cut into alternating blocks of ``block`` samples: even blocks fit each candidate,
   odd blocks judge it.  Score on held-out blocks = Gaussian negative log-likelihood with the noise
   floor the candidate expects, plus k log(n) (BIC penalty, k fitted parameters).  The nuisance is
   fitted too: the rail's fault curve scaled in mu and in creep (``candidates.RAIL``), the most
   common real gap.  Graded answer (``judge``), every row of the ranking with its form, share of the
   held-out gap removed, parameter interval (``candidates.interval_halfwidths``) and at-bound flag:
   - the rail curve removes >= ``MIN_SHRINK`` and no effect beats it by the margin: "the rail's curve
     differs: peak mu -2 %" (named "none", confidence "nuisance");
   - the best effect and the rail curve both remove >= ``MIN_SHRINK`` and neither beats the other:
     "rail or axle load: not separable in this log" (named "none", confidence "not_separable");
   - the best effect removes >= ``MIN_SHRINK``, gains ``MIN_SCORE_GAIN`` over the nominal model, beats
     the runner-up and the rail curve by the margin (``beats``: a held-out score better by
     ``MIN_MARGIN`` and a remaining gap at most ``MARGIN_GAP_RATIO`` of theirs) and its fit is not
     pinned (every parameter at a bound): named (confidence "confident");
   - it removes >= ``MIN_SHRINK`` without that margin: "none named with confidence: most likely X"
     ("tentative"); otherwise "none of the candidates" ("none").
   A quantiser changes the noise, not the mean, so it is judged apart and first (``quantiser``): speeds
   on a lattice coarser than the scenario's own name it beside whatever explains the mean, and its
   noise (q^2 / 12) joins every model's noise floor.
   No noise-floor test: an effect written with other equations than its candidate leaves a
   remainder above the noise and is still the right answer when it beats every alternative.
4. HOW FAR: held-out RMSE per signal before/after; "gap RMSE" = sqrt(max(RMSE^2 - noise floor^2, 0)),
   the part a model can remove; shrink = 1 - gap_after / gap_before.  Identification outcome (RT, peak
   errors, identified curve) on the real run vs the TCU run on the nominal and augmented models' replays.
"""
from __future__ import annotations

import dataclasses
import math
import sys

import numpy as np
from scipy import stats

from identifier import SensorReading, TractionIdentifier
from identifier.metrics import peak_errors, rt_percent
from plant import SensorModel

from ..trace import clean
from ..effects import EFFECTS
from .candidates import (RAIL, SIGNALS, UNITS, Context, Fit, PlantCandidate, SensorDelayCandidate, candidates,
                         fit_nominal, fit_pair, plant_side)
from .model import ObserverReplica, Simulator, initial_line
from .sparse import describe_residual

NONE = "none"
MIN_SHRINK = 0.8           # fraction of the held-out gap a named effect must remove
MIN_MARGIN = 25.0          # held-out score by which it must beat the runner-up and the nuisance, and ...
MARGIN_GAP_RATIO = 0.5     # ... the gap it leaves must be at most this fraction of theirs, unless ...
NOISE_GAP = 0.5            # ... theirs is already this close to the noise floor (noise units)
FORWARD_MIN_SHARE = 0.15   # forward selection starts from a best single effect removing at least this, and
FORWARD_MAX_SHARE = 0.9    # ... and below this (a form that differs from its candidate's leaves up to ~8 %:
                           #     a second effect fitted into that remainder would be a false name) unless ...
FORWARD_MIN_LEFT = 2.5     # ... it leaves at least this many noise units (above what a form's misfit leaves)
FORWARD_MIN_REMAINDER = 0.5  # accepts a second one removing at least this fraction of what the first left
FORWARD_JOINT = 3          # pairs fitted together: the best this many forms of a plant first, or plant seconds
MIN_SCORE_GAIN = 25.0      # held-out NLL + BIC penalty improvement over the nominal model
QUANTUM_OVER_SCENARIO = 1.5  # a lattice of speeds this many times the scenario's own quantum is a quantiser to name
MIN_GAP = 0.5              # combined gap (noise units) below which there is no gap to explain
                           # (measured on nominal runs: up to about 0.3 from the noise alone)
WHERE_SIGNIFICANT = 2.0    # a stage's residual RMS (noise units) from which the gap counts as significant there
WHERE_MIN_PERIODS = 10     # ... over at least this many periods
CREEP_BANDS_KMH = (0.0, 0.5, 1.0, 1.5, 3.0, 10.0, math.inf)
FREQ_BANDS_HZ = (0.0, 2.0, 10.0, 30.0, 100.0, math.inf)
REPLAY_SEEDS = (424242, 424243, 424244, 424245, 424246)   # sensor-noise draws of the identification replays


def _log(progress, msg):
    if progress:
        print(f"hil gap: {msg}", file=sys.stderr, flush=True)


def stages(t_s, creep_kmh, fault_time_s, peak_creep_kmh) -> np.ndarray:
    """0 normal, 1 early, 2 serious per sample (serious from the first creep >= peak after t_f)."""
    out = np.zeros(len(t_s), int)
    after = t_s >= fault_time_s - 1e-12
    out[after] = 1
    over = np.flatnonzero(after & (creep_kmh >= peak_creep_kmh))
    if over.size:
        out[over[0]:] = 2
    return out


def ljung_box(x, lags: int = 20) -> tuple[float, float]:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    n = x.size
    if n <= lags + 2 or np.std(x) == 0:
        return math.nan, math.nan
    x = x - x.mean()
    den = float(np.dot(x, x))
    rho = np.array([np.dot(x[k:], x[:-k]) / den for k in range(1, lags + 1)])
    q = n * (n + 2) * float(np.sum(rho ** 2 / (n - np.arange(1, lags + 1))))
    return q, float(stats.chi2.sf(q, lags))


def max_xcorr(resid, reg, max_lag: int = 20) -> float | None:
    """max |normalised cross-correlation| of residual with a regressor over lags 0..max_lag (regressor
    leading); None if the regressor does not vary."""
    r = np.asarray(resid, float)
    x = np.asarray(reg, float)
    ok = np.isfinite(r) & np.isfinite(x)
    r, x = r[ok], x[ok]
    if r.size < max_lag + 10 or np.std(x) < 1e-12 or np.std(r) == 0:
        return None
    r = (r - r.mean()) / r.std()
    x = (x - x.mean()) / x.std()
    n = r.size
    return float(max(abs(np.dot(r[k:], x[:n - k]) / n) for k in range(max_lag + 1)))


def band_rms(x, period_s, bands) -> list[float]:
    """RMS of x inside each frequency band (Parseval on the one-sided FFT)."""
    x = np.asarray(x, float)
    x = x - x.mean()
    n = x.size
    spec = np.fft.rfft(x)
    f = np.fft.rfftfreq(n, period_s)
    power = np.abs(spec) ** 2 / n ** 2
    if n % 2 == 0:
        power[1:-1] *= 2
    else:
        power[1:] *= 2
    out = []
    for lo, hi in zip(bands[:-1], bands[1:]):
        sel = (f >= lo) & (f < hi)
        out.append(float(math.sqrt(power[sel].sum())))
    return out


#: effects (and parts of effects) that cannot show under a constant torque command, with the excitation
#: that makes them show
NEEDS_VARYING_TORQUE = {
    "torque_lag": "a first-order torque lag acts only when the command changes",
    "compliance.backlash_rad": "gear backlash acts only when the shaft torque changes sign",
}
EXCITATION = ("a torque command that varies: a PRBS dither of a few % or torque steps (the TCU's command is "
              "constant in hil run logs)")


def observability(input_constant: bool) -> list[dict]:
    """What this log cannot show: under a constant command, ``NEEDS_VARYING_TORQUE``; an effect there
    is 'not observable' (its absence from the answer says nothing), with the excitation that shows it."""
    if not input_constant:
        return []
    return [{"effect": k, "why": v, "excitation": EXCITATION} for k, v in NEEDS_VARYING_TORQUE.items()]


# -- the diagnosis --------------------------------------------------------------------------------------
class Diagnosis:
    def __init__(self, data, scenario, *, block: int = 20, max_creep_kmh: float = 8.0, identify: bool = True,
                 progress: bool = False, exclude=()):
        """``exclude``: effect names (forms) not to offer as candidates (the blind bench holds the
        truth's own form out)."""
        self.exclude = tuple(exclude)
        self.quantiser_fit = None
        self.data = data
        self.scenario = scenario
        self.block = block
        self.max_creep_kmh = max_creep_kmh
        self.identify = identify
        self.progress = progress

    def run(self) -> dict:
        d, sc = self.data, self.scenario
        if abs(d.period_s - sc.run.exchange_period_s) > 1e-9:
            from ..errors import ConfigError
            raise ConfigError(f"{d.path}: exchange period {d.period_s} s differs from the model scenario's "
                            f"{sc.run.exchange_period_s} s ({sc.path})")
        settings = sc.identifier_settings()
        obs = ObserverReplica(settings)
        sens = sc.sensors
        s_m = math.sqrt(sens.motor_speed_noise_rad_s ** 2 + sens.motor_speed_quantum_rad_s ** 2 / 12) or 1e-4
        s_t = math.sqrt(sens.train_speed_noise_ms ** 2 + sens.train_speed_quantum_ms ** 2 / 12) or 1e-5
        floors = lambda m, t: {"motor": m, "train": t, "mu_hat": obs.noise_gain() * m}  # noqa: E731
        sigma = floors(s_m, s_t)
        x0, x0_slope = initial_line(d.t_s, d.motor_speed_rad_s, d.train_speed_ms)
        creep_meas = obs.creep_kmh(d.motor_speed_rad_s, d.train_speed_ms)
        # analysis window: until the measured creep first exceeds max_creep_kmh (free spinning after)
        over = np.flatnonzero(creep_meas > self.max_creep_kmh)
        end = int(over[0]) if over.size else d.n
        end = max(end, min(d.n, 100))
        window = np.zeros(d.n, bool)
        window[:end] = True
        blocks = (np.arange(d.n) // self.block) % 2
        train_mask, held_mask = window & (blocks == 0), window & (blocks == 1)
        ctx = Context(d, sc, obs, x0, window, train_mask, held_mask, sigma, x0_slope)

        _log(self.progress, f"replaying the nominal model over {d.n} periods")
        nom_fit = fit_nominal(ctx)
        motor0, train0 = nom_fit.extra["plant_motor"], nom_fit.extra["plant_train"]
        nominal = dict(nom_fit.pred, plant_motor=motor0, plant_train=train0)

        # WHERE: the nominal model from the initial state measured in normal running (fitted on the
        # samples before the fault time only, so a gap after the fault cannot bend it)
        m_line, t_line = self.normal_running_replay(ctx)
        where = self.where(ctx, ctx.predict(m_line, t_line), m_line, t_line, creep_meas)

        # a quantiser first: it changes the noise, not the mean, so when the speeds sit on a lattice it is
        # named apart, and its noise joins every model's floor (else it is a gap the mean models must explain)
        cands = candidates(sc, self.exclude)
        lattice = self.quantiser(ctx, nom_fit, cands)
        if lattice:
            self.exclude = self.exclude + ("sensor_quantisation",)          # forward selection's list too
            cands = [c for c in cands if c.name != "sensor_quantisation"]
            q = lattice["params"]
            base0 = self.score(ctx, nom_fit)
            sigma.update(floors(math.sqrt(s_m ** 2 + q["motor_quantum_rad_s"] ** 2 / 12),     # in place:
                                math.sqrt(s_t ** 2 + q["train_quantum_ms"] ** 2 / 12)))   # ctx.sigma_nom is sigma
            nom_fit = fit_nominal(ctx)
            motor0, train0 = nom_fit.extra["plant_motor"], nom_fit.extra["plant_train"]
            nominal = dict(nom_fit.pred, plant_motor=motor0, plant_train=train0)
            gap0, gap1 = base0["gap"], self.score(ctx, nom_fit)["gap"]
            lattice["share"] = 1 - gap1 / gap0 if gap0 > 0 else 0.0
            lattice["noise_floor"] = dict(sigma)
        fits = []
        for cand in cands:
            _log(self.progress, f"fitting candidate {cand.name}")
            try:
                fit = cand.fit(ctx, nom_fit)
            except Exception as e:  # noqa: BLE001 - a candidate that cannot be fitted is reported, not fatal
                fit = Fit(cand.name, {}, 1, {k: nominal[k] for k in SIGNALS}, dict(sigma), note=f"fit failed: {e}")
            fits.append(fit)
        base = self.score(ctx, nom_fit)
        gap_present = base["gap"] >= MIN_GAP
        # the nuisance first: the rail's fault curve scaled (only when there is a gap to explain)
        rail, rail_fit = None, None
        if gap_present:
            _log(self.progress, "fitting the nuisance: the rail's fault curve (scale in mu and creep)")
            try:
                rail_fit = RAIL.fit(ctx, nom_fit)
                rail = self._entry(ctx, rail_fit, base)
            except Exception as e:  # noqa: BLE001 - reported, not fatal
                rail = None
                _log(self.progress, f"rail curve fit failed: {e}")
        ranking = [self._entry(ctx, fit, base) for fit in fits]
        ranking.sort(key=lambda r: -r["score_gain"])
        best = ranking[0]
        named, named_set, verdict, nuisances, confidence = self.judge(base, ranking, rail, gap_present)
        best_fit = next(f for f in fits if f.name == best["candidate"])
        forward = None
        if gap_present and FORWARD_MIN_SHARE <= best["held_out_shrink"] and best["held_out_gap"] > NOISE_GAP and \
                (best["held_out_shrink"] < FORWARD_MAX_SHARE or best["held_out_gap"] >= FORWARD_MIN_LEFT):
            forward = self.forward(ctx, nom_fit, base, best_fit, best, rail_fit, rail, ranking)
            if forward is not None and forward["accepted"]:
                named, named_set, verdict, confidence = self.rejudge(named, named_set, verdict, confidence, best,
                                                                     forward, ranking)
        if lattice:
            # named beside whatever explains the mean
            named_set = sorted(named_set + ["sensor_quantisation"])
            said = ("the speed sensors are quantised: " + ", ".join(f"{k}={v:.4g}" for k, v in lattice["params"].items()
                                                                     if v > 0)
                    + f" ({lattice['note']}); their noise is {lattice['share'] * 100:.0f} % of the held-out gap")
            if named == NONE:
                named, confidence = "sensor_quantisation", "confident"
                verdict = f"{said}; beyond it, {verdict}"
            else:
                verdict = f"{verdict}; and {said}"
        shrink_table = {s: {"rmse_before": base["per_signal"][s]["rmse"], "rmse_after": best["per_signal"][s]["rmse"],
                            "gap_before": base["per_signal"][s]["gap"], "gap_after": best["per_signal"][s]["gap"],
                            "noise_floor": sigma[s], "unit": UNITS[s]} for s in SIGNALS}
        unobservable = observability(where["input_constant"])
        # what the nominal model leaves, described by a sparse regression (when there is a gap)
        description = describe_residual(ctx.meas["motor"], nominal["motor"], d.train_speed_ms, creep_meas,
                                        d.torque_cmd_nm, d.period_s, ctx.train, ctx.held) if gap_present else None
        out = {
            "real_log": d.path, "real_log_source": d.source, "model": sc.path, "periods": d.n, "analysis_periods": int(window.sum()),
            "held_out_periods": int(held_mask.sum()), "block_periods": self.block,
            "noise_floor": sigma, "initial_state": {"motor_speed_rad_s": nom_fit.extra["x0"][0],
                                                    "train_speed_ms": nom_fit.extra["x0"][1]},
            "where": where,
            "which": {"named": named, "named_set": named_set, "verdict": verdict, "gap_present": gap_present,
                      "confidence": confidence, "nominal_held_out_gap": base["gap"], "ranking": ranking,
                      "nuisances": nuisances, "forward": forward, "unobservable": unobservable,
                      "quantiser": lattice,
                      "description": description,
                      "rule": {"min_shrink": MIN_SHRINK, "min_score_gain": MIN_SCORE_GAIN,
                               "margin_score": MIN_MARGIN, "margin_gap_ratio": MARGIN_GAP_RATIO,
                               "min_gap": MIN_GAP}},
            "shrink": {"effect": best["effect"], "named": named, "held_out_gap_shrink_percent":
                       best["held_out_shrink"] * 100, "per_signal": shrink_table},
        }
        if named == "sensor_quantisation":      # the quantiser alone: its share of the gap is the shrink
            out["shrink"].update(effect="sensor_quantisation", held_out_gap_shrink_percent=lattice["share"] * 100)
        if self.identify:
            _log(self.progress, "identification on the real run and on the model replays")
            augmented = self.quantiser_fit if named == "sensor_quantisation" else best_fit if named != NONE else None
            out["identification"] = self.identification(ctx, nom_fit, augmented,
                                                        creep_meas)
        self.arrays = {"t": d.t_s, "meas": ctx.meas, "nominal": nominal, "best": best_fit.pred, "best_name":
                       best_fit.name, "creep": creep_meas, "window": window, "sigma": sigma,
                       "held": held_mask}
        self.ctx, self.fits, self.nominal = ctx, fits, nominal
        self.base, self.rail, self.ranking = base, rail, ranking
        return clean(out)

    def quantiser(self, ctx: Context, nom_fit: Fit, cands) -> dict | None:
        """The quantisation candidate's fit when the measured speeds sit on a lattice (coherence > 0.9, so
        never on continuous readings) at least ``QUANTUM_OVER_SCENARIO`` times the scenario's own quantum:
        {"params", "note"}; else None (and None when the candidate is not in ``cands``)."""
        cand = next((c for c in cands if c.name == "sensor_quantisation"), None)
        if cand is None:
            return None
        _log(self.progress, "fitting candidate sensor_quantisation (judged apart: it changes the noise)")
        try:
            fit = cand.fit(ctx, nom_fit)
        except Exception:  # noqa: BLE001 - no lattice found then; the candidate is fitted again with the rest
            return None
        sens = self.scenario.sensors
        own = {"motor_quantum_rad_s": sens.motor_speed_quantum_rad_s, "train_quantum_ms": sens.train_speed_quantum_ms}
        if not any(q > 0 and q >= QUANTUM_OVER_SCENARIO * own.get(k, 0.0) for k, q in fit.params.items()):
            return None
        self.quantiser_fit = fit       # the augmented replay of a quantiser-only answer
        return {"params": dict(fit.params), "note": fit.note}

    def normal_running_replay(self, ctx: Context):
        """The nominal model fitted on the pre-fault samples only: the reference of the WHERE statistics."""
        d = self.data
        pre = ctx.window & (d.t_s < self.scenario.run.fault_time_s)
        if pre.sum() < 20:
            return ctx.simulator(None, (), {}).run([], ctx.x0, d.torque_cmd_nm)
        fit = fit_nominal(ctx, pre)
        return fit.extra["plant_motor"], fit.extra["plant_train"]

    def _entry(self, ctx: Context, fit: Fit, base: dict) -> dict:
        """One ranking row: held-out score gain and shrink against the nominal model, form, interval."""
        sc_ = self.score(ctx, fit)
        shrink = 1 - sc_["gap"] / base["gap"] if base["gap"] > 0 else 0.0
        spec = EFFECTS.get(fit.name)
        return {"effect": spec.effect_class if spec else fit.name, "form": spec.form if spec else "",
                "candidate": fit.name, "params": fit.params, "k": fit.k,
                "score_gain": base["score"] - sc_["score"], "held_out_shrink": shrink,
                "share": min(max(shrink, 0.0), 1.0), "held_out_gap": sc_["gap"],
                "held_out_gap_own_floor": sc_["gap_own_floor"], "at_bound": fit.extra.get("at_bound", {}),
                "param_ci": fit.extra.get("param_ci", {}), "note": fit.note, "per_signal": sc_["per_signal"]}

    @staticmethod
    def beats(a: dict, b: dict) -> bool:
        """``a`` explains the held-out data better than ``b`` by the margin: a better held-out score by
        MIN_MARGIN and a remaining gap at most MARGIN_GAP_RATIO of ``b``'s (unless ``b``'s is already
        within the noise: then the score alone decides)."""
        if b["score_gain"] + MIN_MARGIN > a["score_gain"]:
            return False
        return a["held_out_gap"] <= MARGIN_GAP_RATIO * b["held_out_gap"] or b["held_out_gap"] <= NOISE_GAP

    @staticmethod
    def beats_on_top(a: dict, b: dict, first: dict) -> bool:
        """Second effect ``a`` beats second effect ``b`` on top of ``first``: a better held-out score by
        MIN_MARGIN, and either it leaves at most MARGIN_GAP_RATIO of what ``b`` leaves (``beats``' rule)
        or it removes at least 1 / MARGIN_GAP_RATIO times as much of the gap ``first`` left (the margin
        judged on what is left to explain: the first rule is out of reach of a right second effect when
        its form differs from the truth's and leaves a remainder of its own; the second alone is out of
        reach of a right second that removes everything when ``b`` removes more than half)."""
        if b["score_gain"] + MIN_MARGIN > a["score_gain"]:
            return False
        left = first["held_out_gap"]
        return (a["held_out_gap"] <= MARGIN_GAP_RATIO * b["held_out_gap"]
                or MARGIN_GAP_RATIO * (left - a["held_out_gap"]) >= left - b["held_out_gap"])

    def judge(self, base, ranking, rail, gap_present):
        """(named, named_set, verdict, nuisances, confidence) -- see the module docstring, step 3."""
        best = ranking[0]
        runner = next((r for r in ranking[1:] if r["effect"] != best["effect"]), None)   # another class's best
        nuisances = []
        if rail is not None:
            p = rail["params"]
            nuisances.append({"name": "rail_curve", "params": p, "score_gain": rail["score_gain"],
                              "held_out_shrink": rail["held_out_shrink"], "held_out_gap": rail["held_out_gap"],
                              "at_bound": rail["at_bound"], "param_ci": rail["param_ci"],
                              "peak_mu_percent": (p["peak_mu_scale"] - 1) * 100,
                              "peak_creep_percent": (p["creep_scale"] - 1) * 100})
        if not gap_present:
            return NONE, [], (f"no significant gap: held-out residuals are within {base['gap']:.2f} noise units of "
                              f"the sensor noise floor"), nuisances, "none"
        desc = (f"{best['effect']} ({best['form']}) removes {best['share'] * 100:.0f} % of the held-out gap, leaves "
                f"{best['held_out_gap']:.2f} noise units, fitted "
                + ", ".join(f"{k}={v:.4g}" for k, v in best["params"].items()))
        material = best["held_out_shrink"] >= MIN_SHRINK and best["score_gain"] > MIN_SCORE_GAIN
        over_runner = runner is None or self.beats(best, runner)
        rail_material = rail is not None and rail["held_out_shrink"] >= MIN_SHRINK and \
            rail["score_gain"] > MIN_SCORE_GAIN
        over_rail = rail is None or self.beats(best, rail)
        bounded = [k for k, v in best["at_bound"].items() if v]
        bound_note = f" (fit at its bound: {', '.join(bounded)})" if bounded else ""
        # a fit with every parameter at a bound is pinned (the effect vanishes or runs off its range): no
        # name; one parameter of several at a bound (viscous loss 0 beside a Coulomb loss) is only said
        pinned = bool(bounded) and len(bounded) == len(best["at_bound"])
        if rail_material and (rail is not None and (not material or self.beats(rail, best))):
            n = nuisances[0]
            return NONE, [], (f"the rail's curve differs: peak mu {n['peak_mu_percent']:+.1f} %, peak creep "
                              f"{n['peak_creep_percent']:+.1f} % removes {rail['share'] * 100:.0f} % of the held-out "
                              f"gap, more than any effect (best: {desc})"), nuisances, "nuisance"
        if material and rail_material and not over_rail:
            return NONE, [], (f"rail or {self._what(best['effect'])}: not separable in this log (the rail's curve "
                              f"scaled by {nuisances[0]['peak_mu_percent']:+.1f} % removes "
                              f"{rail['share'] * 100:.0f} %, {desc})"), nuisances, "not_separable"
        if material and over_runner and over_rail and not pinned:
            return best["effect"], [best["effect"]], (f"{best['effect']} explains the gap: {desc}{bound_note}"), nuisances, \
                "confident"
        if material:
            why = "its fit sits at a bound" if pinned else (
                f"it does not beat {runner['effect']} ({runner['share'] * 100:.0f} %) by the margin" if not over_runner
                else "it does not beat the rail-curve nuisance by the margin")
            return NONE, [], (f"none named with confidence: most likely {desc}{bound_note}; {why}"), nuisances, \
                "tentative"
        return NONE, [], (f"none of the candidates: the best, {desc}, removes less than "
                          f"{MIN_SHRINK * 100:.0f} %{bound_note}"), nuisances, "none"

    # -- forward selection -----------------------------------------------------------------------------
    def forward(self, ctx: Context, nom_fit: Fit, base: dict, first: Fit, first_row: dict, rail_fit, rail,
                ranking) -> dict:
        """Second step of forward selection: every form of every other class fitted on top of the first
        (its parameters held), judged on held-out data against the first alone.  Sensor-level pairs are not
        tried (a delay on a delay is one delay).  Accepted when the best second effect removes at least
        ``FORWARD_MIN_REMAINDER`` of what the first left, gains ``MIN_MARGIN`` in held-out score, beats the
        best second effect of another class by the margin (``beats_on_top``) and its fit is not pinned at
        its bounds; the pair is then compared with the rail curve plus the same second effect."""
        if first.name == "sensor_quantisation":
            return None
        sensor_first = "plant" not in first.extra
        ctx2 = ctx.on_top_of(first)
        pseudo = self._pseudo(first, nom_fit)
        rows, fits2 = [], {}
        # a second effect of another class, in each of its forms (the form that explains most alone is not
        # always the one that explains most of what the first left)
        by_name = {c.name: c for c in candidates(self.scenario, self.exclude)}
        first_cand = by_name.get(first.name)
        joint = set()         # seconds already fitted together with the first
        first_forms = [r for r in ranking if r["effect"] == first_row["effect"]
                       and isinstance(by_name.get(r["candidate"]), PlantCandidate)][:FORWARD_JOINT]
        for cand in by_name.values():
            if EFFECTS[cand.name].effect_class == first_row["effect"] or \
                    cand.name == "torque_lag" and self.data.torque_cmd_nm.std() < 1e-9:
                continue
            if sensor_first and not isinstance(cand, PlantCandidate):
                continue
            _log(self.progress, f"forward selection: {cand.name} on top of {first.name}")
            try:
                f2 = cand.fit(ctx2, pseudo)
            except Exception:  # noqa: BLE001 - a candidate that cannot be fitted is skipped here
                continue
            row = self._entry(ctx, f2, base)
            if isinstance(first_cand, PlantCandidate) and isinstance(cand, SensorDelayCandidate):
                # a plant effect fitted alone absorbs part of a sensor delay (a lag looks like a delay), so
                # the delay on top finds little of it: fit the pair together for every sensor form, with
                # the first class's best FORWARD_JOINT forms (the form best alone need not be best in a pair)
                for r1 in first_forms:
                    try:
                        c1 = by_name[r1["candidate"]]
                        _log(self.progress, f"forward selection: {c1.name} and {cand.name} fitted together")
                        jf = fit_pair(ctx, c1, cand, r1["params"], f2.extra[cand.ARGUMENT[cand.form]],
                                      f2.extra["x0"])
                        jrow = self._entry(ctx, jf, base)
                        if jrow["score_gain"] > row["score_gain"]:
                            row = dict(jrow, first_params=jf.extra["plant_params"], first_form=r1["form"])
                            joint.add(cand.name)
                    except Exception:  # noqa: BLE001 - keep the greedy fit
                        pass
            fits2[cand.name] = f2
            rows.append(row)
        if not rows:
            return None
        rows.sort(key=lambda r: -r["score_gain"])
        if isinstance(first_cand, SensorDelayCandidate):
            # and a sensor form fitted alone absorbs part of a lag: the best FORWARD_JOINT plant seconds are
            # fitted together with it
            for i, row in enumerate(rows[:FORWARD_JOINT]):
                cand = by_name[row["candidate"]]
                if not isinstance(cand, PlantCandidate):
                    continue
                try:
                    _log(self.progress, f"forward selection: {cand.name} and {first.name} fitted together")
                    f2 = fits2[cand.name]
                    jf = fit_pair(ctx, cand, first_cand, f2.params, first.extra[first_cand.ARGUMENT[first_cand.form]],
                                  f2.extra["x0"])
                    jrow = self._entry(ctx, plant_side(jf, cand), base)
                    if jrow["score_gain"] > row["score_gain"]:
                        rows[i] = dict(jrow, first_params=jf.params)
                        joint.add(cand.name)
                except Exception:  # noqa: BLE001 - keep the greedy fit
                    pass
            rows.sort(key=lambda r: -r["score_gain"])
        second = rows[0]
        runner = next((r for r in rows[1:] if r["effect"] != second["effect"]), None)   # another class's best
        # the first was fitted alone and absorbed part of the second: refit each on top of the other
        # (one round of coordinate descent), keeping the refit only if it scores better
        f1_now, f2_now = first, fits2[second["candidate"]]      # the pair as it stands
        if second["candidate"] not in joint:     # (a second fitted together with the first is done)
            try:
                f2 = f2_now
                _log(self.progress, f"forward selection: refitting {first.name} on top of {f2.name}, then back")
                f1b = by_name[first.name].fit(ctx.on_top_of(f2), self._pseudo(f2, nom_fit))
                f2b = by_name[f2.name].fit(ctx.on_top_of(f1b), self._pseudo(f1b, nom_fit))
                row = self._entry(ctx, f2b, base)
                if row["score_gain"] > second["score_gain"]:
                    second = row
                    second["first_params"] = f1b.params
                    f1_now, f2_now = f1b, f2b
            except Exception:  # noqa: BLE001 - keep the greedy pair
                pass
            # a plant effect and a sensor form: fit both together, from where the pair stands
            try:
                c1, c2 = by_name[first.name], by_name[second["candidate"]]
                plant_c, sensor_c, plant_f, sensor_f = (c1, c2, f1_now, f2_now) if isinstance(c1, PlantCandidate) \
                    else (c2, c1, f2_now, f1_now)
                if isinstance(plant_c, PlantCandidate) and isinstance(sensor_c, SensorDelayCandidate):
                    _log(self.progress, f"forward selection: {plant_c.name} and {sensor_c.name} fitted together")
                    jf = fit_pair(ctx, plant_c, sensor_c, plant_f.params,
                                  sensor_f.extra[SensorDelayCandidate.ARGUMENT[sensor_c.form]], f2_now.extra["x0"])
                    if c2.name == sensor_c.name:          # the second is the sensor form: the row as it is
                        row, first_params = self._entry(ctx, jf, base), jf.extra["plant_params"]
                    else:                                 # the second is the plant effect: name the row after it
                        row, first_params = self._entry(ctx, plant_side(jf, plant_c), base), jf.params
                    if row["score_gain"] > second["score_gain"]:
                        second = row
                        second["first_params"] = first_params
            except Exception:  # noqa: BLE001 - keep the pair as it is
                pass
        removed = 1 - second["held_out_gap"] / first_row["held_out_gap"] if first_row["held_out_gap"] > 0 else 0.0
        bounded = [k for k, v in second["at_bound"].items() if v]
        bounded = bounded if len(bounded) == len(second["at_bound"]) else []      # pinned, as in ``judge``
        accepted = (second["score_gain"] - first_row["score_gain"] >= MIN_MARGIN and removed >= FORWARD_MIN_REMAINDER
                    and (runner is None or self.beats_on_top(second, runner, first_row)) and not bounded
                    and second["held_out_shrink"] >= MIN_SHRINK)
        out = {"first": first_row["effect"], "first_form": second.get("first_form", first_row["form"]),
               "second": second["effect"],
               "second_form": second["form"],
               "second_params": second["params"], "first_params": second.get("first_params", first.params),
               "pair_held_out_shrink": second["held_out_shrink"],
               "second_removes_of_remainder": removed, "accepted": bool(accepted),
               "ranking": [{k: r[k] for k in ("effect", "form", "params", "score_gain", "held_out_shrink",
                                              "held_out_gap", "at_bound")} for r in rows]}
        if accepted and rail_fit is not None:
            # is the first effect the rail in disguise?  the rail curve plus the same second effect
            try:
                cand = by_name[second["candidate"]]
                r2 = cand.fit(ctx.on_top_of(rail_fit), Fit("rail_curve", rail_fit.params, 0, rail_fit.pred,
                                                            dict(ctx.sigma_nom), extra={
                                                                "x0": rail_fit.extra["x0"],
                                                                "plant_motor": rail_fit.extra["plant_motor"],
                                                                "plant_train": rail_fit.extra["plant_train"]}))
                row = self._entry(ctx, r2, base)
                out["rail_pair"] = {"held_out_shrink": row["held_out_shrink"], "score_gain": row["score_gain"],
                                    "held_out_gap": row["held_out_gap"]}
                out["pair_vs_rail"] = ("pair" if self.beats(second, row) else
                                       "rail" if self.beats(row, second) else "not_separable")
            except Exception:  # noqa: BLE001
                out["pair_vs_rail"] = "pair"
        else:
            out["pair_vs_rail"] = "pair"
        return out

    @staticmethod
    def _pseudo(fit: Fit, nom_fit: Fit) -> Fit:
        """``fit`` as the 'nominal' another candidate builds on (its plant trajectory and start)."""
        return Fit(fit.name, fit.params, 0, fit.pred, dict(fit.sigma),
                   extra={"x0": fit.extra["x0"],
                          "plant_motor": fit.extra.get("plant_motor", nom_fit.extra["plant_motor"]),
                          "plant_train": fit.extra.get("plant_train", nom_fit.extra["plant_train"])})

    def rejudge(self, named, named_set, verdict, confidence, best, fw, ranking=()):
        """The answer once forward selection accepted a second effect.  A first effect that was only
        "most likely" alone because it did not beat the rail nuisance by the margin is named with the
        second when the pair beats the rail curve with the same second effect (that comparison is the
        test of the first against the rail, now that the second no longer hides in its remainder)."""
        first, second = fw["first"], fw["second"]
        pair = (f"{second} ({fw['second_form']}) on top of {first} ({fw['first_form']}) removes "
                f"{fw['second_removes_of_remainder'] * 100:.0f} % "
                f"of what {first} left (together {fw['pair_held_out_shrink'] * 100:.0f} % of the gap), fitted "
                + ", ".join(f"{k}={v:.4g}" for k, v in fw["second_params"].items()))
        if fw["pair_vs_rail"] == "rail":
            return second, [second], (
                f"{second} explains part of the gap and the rail's curve differs: {pair}; the rail curve with "
                f"{second} explains it better than {first} with {second}"), "confident"
        if fw["pair_vs_rail"] == "not_separable":
            return second, [second], (f"{second} found, and rail or {self._what(first)}: not separable in this log; "
                                      f"{pair}"), "confident"
        runner = next((r for r in ranking if r["effect"] != best["effect"]), None)
        only_the_rail = (runner is None or self.beats(best, runner)) and not any(best["at_bound"].values())
        if confidence == "tentative" and not (only_the_rail and "rail_pair" in fw):
            return second, [second], (f"{second} found; {pair}; {first} is only the most likely first effect "
                                      f"({verdict})"), "confident"
        return first, sorted([first, second]), (f"{first} and {second} explain the gap: {first} ({best['form']}) "
                                                f"removes {best['share'] * 100:.0f} % alone; {pair}"), "confident"

    @staticmethod
    def _what(effect: str) -> str:
        return {"load_transfer": "axle load"}.get(effect, effect)

    # -- scores ---------------------------------------------------------------------------------------
    def score(self, ctx: Context, fit: Fit) -> dict:
        nll, n, gap2, own2 = 0.0, 0, 0.0, 0.0
        per = {}
        for s in SIGNALS:
            sel = ctx.held & ctx.valid[s]
            r = ctx.meas[s][sel] - fit.pred[s][sel]
            if r.size == 0:     # a log without this signal (e.g. no TCU observer topic)
                per[s] = {"rmse": None, "gap": None}
                continue
            sg = fit.sigma[s]
            nll += float(np.sum((r / sg) ** 2) + r.size * 2 * math.log(sg / ctx.sigma_nom[s]))
            n += r.size
            ms = float(np.mean(r ** 2)) if r.size else math.nan
            g2 = max(ms - sg ** 2, 0.0)
            gap2 += g2 / ctx.sigma_nom[s] ** 2
            own2 += g2 / sg ** 2
            per[s] = {"rmse": math.sqrt(ms), "gap": math.sqrt(g2)}
        m = max(sum(1 for s in SIGNALS if per[s]["rmse"] is not None), 1)
        return {"score": nll + fit.k * math.log(max(n, 2)), "gap": math.sqrt(gap2 / m),
                "gap_own_floor": math.sqrt(own2 / m), "per_signal": per}

    # -- where ----------------------------------------------------------------------------------------
    def where(self, ctx: Context, nominal, motor0, train0, creep_meas) -> dict:
        d, sc = self.data, self.scenario
        w = ctx.window
        peak_creep = sc.fault_curve.peak()[0]
        creep_model = ctx.observer.creep_kmh(nominal["motor"], nominal["train"])
        st_meas = stages(d.t_s, creep_meas, sc.run.fault_time_s, peak_creep)
        st_model = stages(d.t_s, creep_model, sc.run.fault_time_s, peak_creep)
        resid = {s: ctx.meas[s] - nominal[s] for s in SIGNALS}
        resid["creep"] = creep_meas - creep_model
        sig = dict(ctx.sigma_nom)
        sig["creep"] = 3.6 * math.hypot(sc.vehicle.wheel_radius_m / sc.vehicle.gear_ratio * sig["motor"], sig["train"])

        def rms(x, sel):
            x = x[sel & np.isfinite(x)]
            return float(np.sqrt(np.mean(x ** 2))) if x.size else None

        per_signal = {s: {"rmse": rms(resid[s], w), "noise_floor": sig[s], "unit": UNITS.get(s, ""),
                          "rmse_in_noise_units": (rms(resid[s], w) or 0) / sig[s]} for s in resid}
        names = ("normal", "early", "serious")
        per_stage = {}
        for i, nm in enumerate(names):
            sel = w & (st_meas == i)
            per_stage[nm] = {"periods": int(sel.sum()),
                             **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                                for s in resid}}

        per_stage_model = {}
        for i, nm in enumerate(names):
            sel = w & (st_model == i)
            per_stage_model[nm] = {"periods": int(sel.sum()),
                                   **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                                      for s in resid}}

        def t_det(stg):
            idx = np.flatnonzero(stg == 2)
            return float(d.t_s[idx[0]] - sc.run.fault_time_s) if idx.size else None

        per_band = []
        for lo, hi in zip(CREEP_BANDS_KMH[:-1], CREEP_BANDS_KMH[1:]):
            sel = w & (creep_meas >= lo) & (creep_meas < hi)
            per_band.append({"creep_kmh": [lo, None if math.isinf(hi) else hi], "periods": int(sel.sum()),
                             **{s: (None if rms(resid[s], sel) is None else rms(resid[s], sel) / sig[s])
                                for s in resid}})
        # frequency bands: residual RMS per band against the noise's own RMS in that band
        rng = np.random.default_rng(7)
        nw = int(w.sum())
        e = rng.standard_normal(nw)
        noise = {"motor": sig["motor"] * e, "train": sig["train"] * rng.standard_normal(nw),
                 "mu_hat": sig["motor"] * (ctx.observer.mu_hat(64.0 + e, np.full(nw, ctx.observer.torque_demand))
                                           - ctx.observer.torque_demand / ctx.observer.torque_per_mu)}
        per_freq = []
        band_res = {s: band_rms(np.nan_to_num(resid[s][w]), d.period_s, FREQ_BANDS_HZ) for s in SIGNALS}
        band_noise = {s: band_rms(noise[s], d.period_s, FREQ_BANDS_HZ) for s in SIGNALS}
        for i, (lo, hi) in enumerate(zip(FREQ_BANDS_HZ[:-1], FREQ_BANDS_HZ[1:])):
            per_freq.append({"hz": [lo, None if math.isinf(hi) else hi],
                             **{s: {"rms": band_res[s][i], "noise_rms": band_noise[s][i],
                                    "ratio": band_res[s][i] / band_noise[s][i] if band_noise[s][i] > 0 else None}
                                for s in SIGNALS}})
        tests = {}
        torque = d.torque_cmd_nm
        for s in SIGNALS:
            q, p = ljung_box(resid[s][w] / sig[s])
            tests[s] = {"ljung_box_q": q, "ljung_box_p": p, "white": bool(p > 0.01) if p == p else None,
                        "xcorr_input": max_xcorr(resid[s][w], torque[w]),
                        "xcorr_model_creep": max_xcorr(resid[s][w], creep_model[w]),
                        "xcorr_bound_95": 1.96 / math.sqrt(max(int(w.sum()), 1))}
        worst_stage = max(per_stage, key=lambda k: max((v or 0) for kk, v in per_stage[k].items()
                                                        if kk in SIGNALS) if per_stage[k]["periods"] else -1)
        worst_band = max(per_band, key=lambda b: max((b[s] or 0) for s in SIGNALS) if b["periods"] else -1)
        worst_freq = max(per_freq, key=lambda b: max((b[s]["ratio"] or 0) for s in SIGNALS))
        worst_signal = max(SIGNALS, key=lambda s: per_signal[s]["rmse_in_noise_units"])
        largest = (f"largest on {worst_signal} ({per_signal[worst_signal]['rmse_in_noise_units']:.1f}x noise), "
                   f"in the {worst_stage} stage, at measured creep {worst_band['creep_kmh'][0]}-"
                   f"{worst_band['creep_kmh'][1] or 'inf'} km/h, in the {worst_freq['hz'][0]}-"
                   f"{worst_freq['hz'][1] or 'Nyquist'} Hz band")
        # the headline: the EARLIEST stage where the gap is significant (the serious stage amplifies any
        # gap), and the frequency band worst within that stage's own samples, among the bands its length
        # resolves (a band is resolved when the stage lasts at least two periods of its lower edge)
        earliest = None
        for i, nm in enumerate(names):
            v = per_stage[nm]
            if v["periods"] >= WHERE_MIN_PERIODS and max((v[s] or 0) for s in SIGNALS) >= WHERE_SIGNIFICANT:
                earliest = (i, nm)
                break
        stage_where = None
        if earliest is not None:
            i, nm = earliest
            sel = w & (st_meas == i)
            dur = float(sel.sum()) * d.period_s
            f_min = 2.0 / dur if dur > 0 else math.inf
            sig_e = max(SIGNALS, key=lambda s: per_stage[nm][s] or 0)
            e2 = np.random.default_rng(11).standard_normal(int(sel.sum()))
            bands = []
            for s_ in SIGNALS:
                res = band_rms(np.nan_to_num(resid[s_][sel]), d.period_s, FREQ_BANDS_HZ)
                nz = band_rms(noise["mu_hat"][:e2.size] if s_ == "mu_hat" else sig[s_] * e2, d.period_s,
                              FREQ_BANDS_HZ)
                for j, (lo, hi) in enumerate(zip(FREQ_BANDS_HZ[:-1], FREQ_BANDS_HZ[1:])):
                    bands.append({"signal": s_, "hz": [lo, None if math.isinf(hi) else hi],
                                  "ratio": res[j] / nz[j] if nz[j] > 0 else None, "resolved": lo == 0 or lo >= f_min})
            resolved = [b for b in bands if b["resolved"] and b["ratio"] is not None and b["hz"][0] > 0]
            worst_b = max(resolved, key=lambda b: b["ratio"]) if resolved else None
            unresolved = sorted({b["hz"][0] for b in bands if not b["resolved"]})
            stage_where = {"stage": nm, "signal": sig_e, "rms_in_noise_units": per_stage[nm][sig_e],
                           "duration_s": dur, "lowest_resolved_hz": f_min, "bands": bands,
                           "worst_band": worst_b}
            summary = (f"first significant in the {nm} stage ({sig_e} {per_stage[nm][sig_e]:.1f}x noise over "
                       f"{dur:.3g} s)")
            if worst_b is not None:
                summary += (f", there worst in the {worst_b['hz'][0]:g}-{worst_b['hz'][1] or 'Nyquist'} Hz band "
                            f"({worst_b['signal']} {worst_b['ratio']:.1f}x the noise in that band)")
            if unresolved:
                summary += (f"; its {dur:.3g} s do not resolve bands below {f_min:.3g} Hz")
            summary += f"; overall {largest}"
        else:
            summary = largest
        return {"summary": summary, "largest": largest, "earliest": stage_where,
                "per_signal": per_signal, "per_stage": per_stage,
                "per_stage_by_model_creep": per_stage_model,
                "t_det_measured_s": t_det(st_meas), "t_det_model_s": t_det(st_model),
                "per_creep_band": per_band, "per_frequency_band": per_freq, "tests": tests,
                "input_constant": bool(np.std(torque) < 1e-9)}

    # -- identification -----------------------------------------------------------------------------
    def _outcome(self, events, creep) -> dict:
        """What an identification run came to (identified, T_det from ``creep``, RT, curve, peak errors)."""
        d, sc = self.data, self.scenario
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

    def identification(self, ctx: Context, nominal, best: Fit | None, creep_meas) -> dict:
        d = self.data
        strategy = d.strategy or "nlls"
        real = {"source": "real run (log)", **self._outcome(d.identification, creep_meas)}
        nom = self.replay(ctx, nominal.extra["plant_motor"], nominal.extra["plant_train"], {}, strategy,
                          "nominal model replay")
        out = {"strategy": strategy, "real": real, "nominal_replay": nom}
        if best is not None:
            x0 = np.array(best.extra["x0"])
            if "plant" in best.extra:
                name, params = best.extra["plant"]
                motor, train = Simulator(ctx.cfg, name, (), params, d.n).run([], x0, d.torque_cmd_nm)
            else:
                motor, train = ctx.simulator(None, (), {}).run([], x0, d.torque_cmd_nm)
            out["augmented_replay"] = self.replay(ctx, motor, train, best.extra, strategy,
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

    def replay(self, ctx: Context, motor, train, extra: dict, strategy: str, label: str) -> dict:
        """The TCU run on a model's speeds (+ candidate delays/quanta) with the scenario's sensor noise,
        once per seed in REPLAY_SEEDS: identification is sensitive to the noise draw, so the median
        and the spread (min, max) are reported; ``params`` are those of the run with the median peak mu."""
        runs = [self._replay_once(ctx, motor, train, extra, strategy, seed) for seed in REPLAY_SEEDS]
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

    def _replay_once(self, ctx: Context, motor, train, extra: dict, strategy: str, seed: int) -> dict:
        d, sc = self.data, self.scenario
        from .model import shift
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
        return self._outcome(events, ctx.observer.creep_kmh(meas[:, 0], meas[:, 1]))


def diagnose(data, scenario, **kw) -> tuple[dict, Diagnosis]:
    dg = Diagnosis(data, scenario, **kw)
    return dg.run(), dg


__all__ = ["diagnose", "Diagnosis", "NONE"]
