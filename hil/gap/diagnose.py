"""Sim-to-real gap diagnosis: where the gap lies, which effect explains it, how far it shrinks.

1. The nominal model (the scenario) is driven by the real log's torque commands from the initial
   state measured in the log (``model.initial_line``: straight-line fits over the first samples).  Its
   mu^ is the TCU's observer applied to the model's speeds.  Residual = measured - model on three
   signals: motor speed, train speed (sensor frames) and the TCU's mu^.  Each is divided by its noise
   floor (the scenario's sensor noise and quantum, sqrt(sigma^2 + q^2 / 12); for mu^ that noise through
   the observer), so 1 means "as good as the sensors".
2. WHERE (``where``): residual RMS per signal, per stage, per creep band and per frequency band, the
   whiteness and cross-correlation tests, and the headline.
3. WHICH (``select``): each candidate fitted on the training blocks and judged on the held-out ones,
   the rail-curve nuisance, the graded answer, a quantiser judged apart, forward selection of a second
   effect, and the sparse description of what the nominal model leaves (``sparse``).  Every candidate
   fit that fails is counted and named (``which.failed_candidates``), never dropped.
4. HOW FAR: held-out RMSE per signal before/after; "gap RMSE" = sqrt(max(RMSE^2 - noise floor^2, 0)),
   the part a model can remove; shrink = 1 - gap_after / gap_before.  Identification outcome
   (``identify``: RT, peak errors, identified curve) on the real run vs the TCU run on the nominal and
   augmented models' replays.

``Diagnosis(data, scenario, ...).run()`` returns a ``DiagnosisResult``: the JSON-ready answer
(``report``) and what the report's plots and the bench's oracle read (context, fits, ranking).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field

import numpy as np

from ..trace import clean
from .calibration import grade_line, read_calibration
from .candidates import SIGNALS, UNITS, Context, Fit, candidates, fit_nominal
from .identify import identification
from .model import ObserverReplica, initial_line
from .select import (FORWARD_MAX_SHARE, FORWARD_MIN_LEFT, FORWARD_MIN_SHARE, MARGIN_GAP_RATIO, MIN_GAP, MIN_MARGIN,
                     MIN_SCORE_GAIN, MIN_SHRINK, NOISE_GAP, NONE, HowFar, Row, Verdict, choose_pair, entry,
                     fit_candidates, fit_rail, forward, judge, label, other_firsts, pair_explanation, pair_label,
                     pair_listed, quantiser, rejudge, score, within_noise)
from .sparse import AHEAD_PERIODS, describe_residual
from .where import normal_running_replay, observability, separation, where


@dataclass
class DiagnosisResult:
    """What one diagnosis found.  ``report``: the answer as plain data (``hil gap --json``); the rest is
    what the report's plots and the bench's oracle read: the context the candidates were judged in,
    the nominal model (``nominal``: its predictions and plant trajectory), the best single candidate's
    fit, every candidate's fit, the nominal model's held-out score (``base``), the rail nuisance's
    ranking row (None without a gap or when its fit failed), the ranking, the measured creep, the
    failed candidate fits (also in ``report["which"]["failed_candidates"]``), and what the sparse
    description's rate view started from (``sparse.view_targets``; None without a gap)."""

    report: dict
    data: object
    scenario: object
    ctx: Context
    nominal: dict
    best: Fit
    fits: list
    base: dict
    rail: dict | None
    ranking: list
    creep_meas: np.ndarray
    failed: list = field(default_factory=list)
    ahead_motor: np.ndarray | None = None     # Simulator.ahead by sparse.AHEAD_PERIODS (the rate view)
    verdict: Verdict | None = None            # the answer (``report["which"]`` and ``["shrink"]`` are it)


def _log(progress, msg):
    if progress:
        print(f"hil gap: {msg}", file=sys.stderr, flush=True)


# -- the diagnosis --------------------------------------------------------------------------------------
class Diagnosis:
    """The diagnosis' settings; ``run`` does it and returns a ``DiagnosisResult`` (nothing is kept here)."""

    def __init__(self, data, scenario, *, block: int = 20, max_creep_kmh: float = 8.0, identify: bool = True,
                 progress: bool = False, exclude=()):
        """``exclude``: effect names (forms) not to offer as candidates (the blind bench holds the
        truth's own form out)."""
        self.exclude = tuple(exclude)
        self.data = data
        self.scenario = scenario
        self.block = block
        self.max_creep_kmh = max_creep_kmh
        self.identify = identify
        self.progress = progress

    def run(self) -> DiagnosisResult:
        d, sc = self.data, self.scenario
        say = lambda msg: _log(self.progress, msg)  # noqa: E731
        failed: list[dict] = []
        exclude = self.exclude
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
        ctx, creep_meas = self._context(obs, sigma)

        say(f"replaying the nominal model over {d.n} periods")
        nom_fit = fit_nominal(ctx)
        motor0, train0 = nom_fit.extra["plant_motor"], nom_fit.extra["plant_train"]
        nominal = dict(nom_fit.pred, plant_motor=motor0, plant_train=train0)

        # WHERE: the nominal model from the initial state measured in normal running (fitted on the
        # samples before the fault time only, so a gap after the fault cannot bend it)
        m_line, t_line = normal_running_replay(ctx)
        where_ = where(ctx, ctx.predict(m_line, t_line), creep_meas)

        # a quantiser first: it changes the noise, not the mean, so when the speeds sit on a lattice it is
        # named apart, and its noise joins every model's floor (else it is a gap the mean models must explain)
        cands = candidates(sc, exclude)
        lattice, quantiser_fit = quantiser(ctx, nom_fit, cands, failed, say)
        if lattice:
            exclude = exclude + ("sensor_quantisation",)          # forward selection's list too
            cands = [c for c in cands if c.name != "sensor_quantisation"]
            q = lattice["params"]
            base0 = score(ctx, nom_fit)
            sigma.update(floors(math.sqrt(s_m ** 2 + q["motor_quantum_rad_s"] ** 2 / 12),     # in place:
                                math.sqrt(s_t ** 2 + q["train_quantum_ms"] ** 2 / 12)))   # ctx.sigma_nom is sigma
            nom_fit = fit_nominal(ctx)
            motor0, train0 = nom_fit.extra["plant_motor"], nom_fit.extra["plant_train"]
            nominal = dict(nom_fit.pred, plant_motor=motor0, plant_train=train0)
            gap0, gap1 = base0["gap"], score(ctx, nom_fit)["gap"]
            lattice["share"] = 1 - gap1 / gap0 if gap0 > 0 else 0.0
            lattice["noise_floor"] = dict(sigma)
        fits = fit_candidates(ctx, nom_fit, cands, failed, say)
        base = score(ctx, nom_fit)
        gap_present = base["gap"] >= MIN_GAP
        # the nuisance first: the rail's fault curve scaled (only when there is a gap to explain)
        rail, rail_fit = None, None
        if gap_present:
            rail_fit, rail = fit_rail(ctx, nom_fit, base, failed, say)
        ranking = sorted((entry(ctx, fit, base) for fit in fits), key=lambda r: -r.score_gain)
        best = ranking[0]
        best_fit = next(f for f in fits if f.name == best.candidate)
        answer = judge(base, ranking, rail, gap_present)
        self._separate(answer, ctx, fits, rail, rail_fit, creep_meas)
        forward_, tried, answer = self._pairs(answer, ctx, nom_fit, base, fits, ranking, rail, rail_fit, exclude,
                                              failed, say, gap_present)
        listed = self._listed(answer, forward_, tried)
        if lattice:
            self._name_quantiser(answer, lattice)
        named_row, far = self._how_far(answer, ranking, best, forward_, lattice, rail)
        # what the nominal model leaves, described by a sparse regression (when there is a gap)
        description, ahead = None, None
        if gap_present:
            ahead = ctx.simulator(None, (), {}).ahead(d.motor_speed_rad_s, d.train_speed_ms, d.torque_cmd_nm,
                                                      AHEAD_PERIODS)
            description = describe_residual(ctx.meas["motor"], nominal["motor"], d.train_speed_ms, creep_meas,
                                            d.torque_cmd_nm, d.period_s, ctx.train, ctx.held, ahead)
        out = self._record(ctx, nom_fit, sigma, where_, base, gap_present, ranking, answer, listed, forward_,
                           tried, failed, lattice, description, far)
        named = answer.named
        if self.identify:
            say("identification on the real run and on the model replays")
            named_fit = next(f for f in fits if f.name == named_row.candidate)
            augmented = quantiser_fit if named == "sensor_quantisation" else named_fit if named != NONE else None
            out["identification"] = identification(ctx, nom_fit, augmented, creep_meas)
        return DiagnosisResult(clean(out), d, sc, ctx, nominal, best_fit, fits, base, rail, ranking, creep_meas,
                               failed, ahead, answer)

    def _context(self, obs, sigma) -> tuple[Context, np.ndarray]:
        """The run cut for the fits (``Context``) and the measured creep: the analysis window runs until
        the measured creep first exceeds ``max_creep_kmh`` (free spinning after; at least 100 periods),
        cut into alternating blocks of ``block`` periods, the even ones fitted, the odd ones held out."""
        d = self.data
        x0, x0_slope = initial_line(d.t_s, d.motor_speed_rad_s, d.train_speed_ms)
        creep_meas = obs.creep_kmh(d.motor_speed_rad_s, d.train_speed_ms)
        over = np.flatnonzero(creep_meas > self.max_creep_kmh)
        end = int(over[0]) if over.size else d.n
        end = max(end, min(d.n, 100))
        window = np.zeros(d.n, bool)
        window[:end] = True
        blocks = (np.arange(d.n) // self.block) % 2
        train_mask, held_mask = window & (blocks == 0), window & (blocks == 1)
        return Context(d, self.scenario, obs, x0, window, train_mask, held_mask, sigma, x0_slope), creep_meas

    def _record(self, ctx, nom_fit, sigma, where_, base, gap_present, ranking, answer: Verdict, listed, forward_,
                tried, failed, lattice, description, far) -> dict:
        """The diagnosis as ``hil gap --json`` prints it (docs/design/gap-diagnosis.md), from the typed
        answer (``Verdict``) and rows: WHERE, WHICH, HOW FAR."""
        d, sc = self.data, self.scenario
        named, confidence = answer.named, answer.grade
        shrink_table = {s: {"rmse_before": base["per_signal"][s]["rmse"], "rmse_after": far.per_signal[s]["rmse"],
                            "gap_before": base["per_signal"][s]["gap"], "gap_after": far.per_signal[s]["gap"],
                            "noise_floor": sigma[s], "unit": UNITS[s]} for s in SIGNALS}
        unobservable = observability(where_["input_constant"])
        window, held_mask = ctx.window, ctx.held
        return {
            "real_log": d.path, "real_log_source": d.source, "model": sc.path, "periods": d.n, "analysis_periods": int(window.sum()),
            "held_out_periods": int(held_mask.sum()), "block_periods": self.block,
            "noise_floor": sigma, "initial_state": {"motor_speed_rad_s": nom_fit.extra["x0"][0],
                                                    "train_speed_ms": nom_fit.extra["x0"][1]},
            "where": where_,
            "which": {"named": named, "named_set": answer.named_set, "verdict": answer.sentence,
                      "gap_present": gap_present,
                      "confidence": confidence, "nominal_held_out_gap": base["gap"],
                      "ranking": [r.to_json() for r in ranking],
                      "not_separable": listed,
                      "separate_by": answer.separate_by[0] if answer.separate_by else None,
                      "separate_by_pairs": answer.separate_by,
                      "nuisances": answer.nuisances, "forward": forward_,
                      "forward_firsts": [{k: fw.get(k) for k in ("first", "first_form", "second", "second_form",
                                                                 "accepted", "own_tests_passed", "rejected_because",
                                                                 "pair_held_out_shrink", "pair_held_out_gap")}
                                         for _, fw in tried], "unobservable": unobservable,
                      "failed_candidates": failed,
                      "calibration": grade_line(confidence, read_calibration()),
                      "quantiser": lattice,
                      "description": description,
                      "rule": {"min_shrink": MIN_SHRINK, "min_score_gain": MIN_SCORE_GAIN,
                               "margin_score": MIN_MARGIN, "margin_gap_ratio": MARGIN_GAP_RATIO,
                               "min_gap": MIN_GAP, "within_noise_gap": NOISE_GAP}},
            "shrink": {"effect": answer.how_far.label, "named": named, "said": answer.how_far.said(),
                       "held_out_gap_shrink_percent": answer.how_far.held_out_shrink * 100,
                       "per_signal": shrink_table},
        }

    # -- the steps of ``run`` after the single candidates are judged ---------------------------------------
    @staticmethod
    def _separate(answer: Verdict, ctx, fits, rail, rail_fit, creep_meas) -> None:
        """What would tell a "not separable" answer's explanations apart: where their fits differ most
        (``answer.separate_by``, the first two explanations' first, said in the sentence)."""
        if not answer.alternatives:
            return
        by_name = {f.name: f for f in fits}
        preds = {label(r): (rail_fit.pred if r is rail else by_name[r.candidate].pred) for r in answer.alternatives}
        answer.separate_by = separation(ctx, preds, creep_meas)
        if answer.separate_by:
            sb = answer.separate_by[0]      # the two best: the first two explanations listed
            answer.sentence += (f"; they differ most on {sb['signal']} in the {sb['stage']} stage "
                                f"({sb['difference_noise_units']:.2f} noise units between {sb['between'][0]} and "
                                f"{sb['between'][1]})")

    @staticmethod
    def _pairs(answer: Verdict, ctx, nom_fit, base, fits, ranking, rail, rail_fit, exclude, failed, say,
               gap_present):
        """Forward selection: (its answer from the best single, every (first row, answer) tried, the
        verdict).  Nothing is named on top of an explanation that leaves the held-out gap within the
        noise: the rail nuisance (``within_noise``) or the best single effect (its gap above NOISE_GAP);
        after a first that removes most of the gap, not within twice that (``FORWARD_MIN_LEFT``: what a
        form that differs from its candidate's leaves, which a small second effect can take half of).
        The pair built on the best single first; when it is not accepted, from the other classes it does
        not beat (``other_firsts``); one accepted pair is named (``rejudge``), several within the margin
        of each other are "not_separable"."""
        best = ranking[0]
        if not (gap_present and FORWARD_MIN_SHARE <= best.held_out_shrink and best.held_out_gap > NOISE_GAP
                and not within_noise(rail)
                and (best.held_out_shrink < FORWARD_MAX_SHARE or best.held_out_gap >= FORWARD_MIN_LEFT)):
            return None, [], answer
        alone = {f.name: f for f in fits}
        forward_ = forward(ctx, nom_fit, base, alone[best.candidate], best, rail_fit, ranking, exclude, failed, say,
                           alone=alone)
        tried = [(best, forward_)] if forward_ is not None else []
        if forward_ is None or not forward_["accepted"]:
            for row in other_firsts(ranking, best):      # the true first need not be the best alone
                fw = forward(ctx, nom_fit, base, alone[row.candidate], row, rail_fit, ranking, exclude, failed, say,
                             alone=alone)
                if fw is not None:
                    tried.append((row, fw))
        first_row, won, rivals = choose_pair(tried)
        if won is None:
            return forward_, tried, answer
        if not rivals:
            return won, tried, rejudge(answer, first_row, won, ranking)   # the pair settles what the singles left
        # pairs on different firsts, each accepted, none beating the others by the margin
        pairs = [won] + rivals
        return won, tried, Verdict(
            "not_separable", " or ".join(pair_label(fw) for fw in pairs) + ": not separable in this log ("
            + "; ".join(f"{pair_label(fw)} removes {fw['pair_held_out_shrink'] * 100:.0f} %, leaves "
                        f"{fw['pair_held_out_gap']:.2f} noise units" for fw in pairs) + ")",
            nuisances=answer.nuisances, alternatives=[pair_listed(fw) for fw in pairs])

    @staticmethod
    def _listed(answer: Verdict, forward_, tried) -> list[dict]:
        """The explanations a "not_separable" answer lists (``which.not_separable``): its rows, or its
        pairs; and a pair forward selection turned away only against the rows listed, as one more."""
        if answer.alternatives and isinstance(answer.alternatives[0], dict):     # pairs (``_pairs``)
            return answer.alternatives
        listed = [{"explanation": label(r), "effect": r.effect, "effects": [r.effect], "form": r.form,
                   "held_out_shrink": r.held_out_shrink, "held_out_gap": r.held_out_gap,
                   "score_gain": r.score_gain} for r in answer.alternatives]
        if answer.grade != "not_separable":
            return listed
        for _, fw in tried:
            pair = pair_explanation(fw, answer.alternatives)
            if pair is None or any(set(p["effects"]) == set(pair["effects"]) for p in listed):
                continue
            listed.append(pair)
            answer.also(f"or {pair['explanation']}, within the margin of them too (removes "
                        f"{pair['held_out_shrink'] * 100:.0f} %, leaves {pair['held_out_gap']:.2f} noise units; "
                        f"not named because {'; '.join(pair['turned_away_because'])})")
        return listed

    @staticmethod
    def _name_quantiser(answer: Verdict, lattice: dict) -> None:
        """A quantiser judged apart is named beside whatever explains the mean (or alone)."""
        answer.named_set = sorted(answer.named_set + ["sensor_quantisation"])
        said = ("the speed sensors are quantised: " + ", ".join(f"{k}={v:.4g}" for k, v in lattice["params"].items()
                                                                 if v > 0)
                + f" ({lattice['note']}); their noise is {lattice['share'] * 100:.0f} % of the held-out gap")
        if answer.named == NONE:
            answer.named, answer.grade = "sensor_quantisation", "confident"
            answer.sentence = f"{said}; beyond it, {answer.sentence}"
        else:
            answer.also(f"and {said}")

    @staticmethod
    def _how_far(answer: Verdict, ranking, best, forward_, lattice, rail):
        """(the named class's best single row, the row HOW FAR reports) and ``answer.how_far``: the
        explanation named (a pair, or that single; the quantiser alone: its share of the gap; the rail
        curve when the answer is that nuisance, issue 51: the best effect's shrink would read as the
        answer), else the best single."""
        named = answer.named
        named_row = next((r for r in ranking if r.effect == named), best)
        if answer.grade == "nuisance" and rail is not None:
            far = rail
        elif forward_ is not None and forward_["accepted"] and set(answer.named_set) - {"sensor_quantisation"} == \
                {forward_["first"], forward_["second"]}:
            far = Row(f"{forward_['first']} + {forward_['second']}", forward_["first_form"],
                      forward_["second_candidate"], {}, 0, forward_["pair_score_gain"],
                      forward_["pair_held_out_shrink"], forward_["pair_held_out_gap"],
                      per_signal=forward_["pair_per_signal"])
        else:
            far = named_row
        answer.how_far = HowFar(far.effect, named != NONE, far.held_out_shrink, far.per_signal)
        if named == "sensor_quantisation":      # the quantiser alone: its share of the gap is the shrink
            answer.how_far.label, answer.how_far.held_out_shrink = "sensor_quantisation", lattice["share"]
        return named_row, far


def diagnose(data, scenario, **kw) -> tuple[dict, DiagnosisResult]:
    """(the answer as plain data, the whole result): ``Diagnosis(data, scenario, **kw).run()``."""
    result = Diagnosis(data, scenario, **kw).run()
    return result.report, result


__all__ = ["diagnose", "Diagnosis", "DiagnosisResult", "NONE"]
