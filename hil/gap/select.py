"""WHICH effect explains the gap: candidate selection, judged on held-out data.

The run is cut into alternating blocks of ``block`` samples: even blocks fit each candidate, odd
blocks judge it.  Score on held-out blocks (``score``) = Gaussian negative log-likelihood with the
noise floor sigma_s the candidate expects, relative to the nominal floor sigma0_s,

    NLL = sum_s sum_k (r_sk / sigma_s)^2 + 2 n_s log(sigma_s / sigma0_s),   score = NLL + k log(n)

(k log(n): the BIC penalty, k fitted parameters).  "Gap" = sqrt(max(RMSE^2 - sigma^2, 0)), the part a
model can remove, in nominal noise units averaged over the signals; shrink = 1 - gap_after / gap_before.
The nuisance is fitted too: the rail's fault curve scaled in mu and in creep (``candidates.RAIL``),
the most common real gap.  Graded answer (``judge``), every row of the ranking with its form, share
of the held-out gap removed, parameter interval (``candidates.interval_halfwidths``) and at-bound flag:

- the explanations are the best candidate of each class and the rail curve (``explanations``); those
  that remove >= ``MIN_SHRINK`` and gain ``MIN_SCORE_GAIN`` are compared.  When the best of them does
  not beat one of another class by the margin (``beats``), the answer lists them all: "the rail curve
  or compliance (viscous_coulomb): not separable in this log" (named "none", confidence
  "not_separable"; the diagnosis adds where their fits differ most, ``where.separation``);
- the rail curve is the best, beats every other by the margin and leaves the held-out gap within the
  noise (``within_noise``: ``NOISE_GAP`` noise units): "the rail's curve differs: peak mu -2 %" (named
  "none", confidence "nuisance").  An effect must then beat it on both counts (``beats_strictly``), and
  nothing is fitted on top of it (no forward selection).  The rail curve best by the margin but leaving
  more than the noise is not the whole story (a constant-power limit of the drive is mimicked so): "none
  of the candidates explains the whole gap", confidence "none" (the rail's fit still listed among the
  nuisances);
- the best effect removes >= ``MIN_SHRINK``, gains ``MIN_SCORE_GAIN`` over the nominal model, beats
  the runner-up and the rail curve by the margin (``beats``: a held-out score better by
  ``MIN_MARGIN`` and a remaining gap at most ``MARGIN_GAP_RATIO`` of theirs) and its fit is not
  pinned (every parameter at a bound): named (confidence "confident");
- it removes >= ``MIN_SHRINK`` without that margin: "none named with confidence: most likely X"
  ("tentative"); otherwise "none of the candidates" ("none").

A quantiser changes the noise, not the mean, so it is judged apart and first (``quantiser``): speeds
on a lattice coarser than the scenario's own name it beside whatever explains the mean, and its noise
(q^2 / 12) joins every model's noise floor.  No noise-floor test: an effect written with other
equations than its candidate leaves a remainder above the noise and is still the right answer when it
beats every alternative.  Two effects: ``forward`` (a second effect on top of the first, pairs fitted
together; the pair must also win on data held out in time, ``time_veto``, and beat its first alone
fitted again from where its fit there landed, ``Forward.first_again``), from the best single and,
when its pair is not accepted, from the other classes it does not beat (``other_firsts``,
``choose_pair``), and ``rejudge``.

A candidate whose fit fails is never dropped silently: each failure (a least-squares start the model
cannot be evaluated at, a model that diverges, a CasADi evaluation error: ``FIT_ERRORS``) is appended
to the caller's ``failed`` list (``failure``: name, form, step, error) and the diagnosis reports them
(``which.failed_candidates``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..effects import EFFECTS
from .candidates import (RAIL, SIGNALS, Context, Fit, PlantCandidate, SensorDelayCandidate, candidates, fit_nominal,
                         fit_pair, plant_side)
from .where import stages

NONE = "none"
MIN_SHRINK = 0.8           # fraction of the held-out gap a named effect must remove
MIN_MARGIN = 25.0          # held-out score by which it must beat the runner-up and the nuisance, and ...
MARGIN_GAP_RATIO = 0.5     # ... the gap it leaves must be at most this fraction of theirs, unless ...
NOISE_GAP = 0.5            # ... theirs is already this close to the noise floor (noise units)
FORWARD_MIN_SHARE = 0.15   # forward selection starts from a best single effect removing at least this, and
FORWARD_MAX_SHARE = 0.9    # ... below this, or (a form that differs from its candidate's leaves a remainder a
FORWARD_MIN_LEFT = 1.0     # ... second may take) leaving at least this many noise units: twice NOISE_GAP
FORWARD_MIN_REMAINDER = 0.5  # accepts a second one removing at least this fraction of what the first left
FORWARD_JOINT = 3          # pairs fitted together: the best this many forms of a plant first, or plant seconds
FORWARD_FIRSTS = 2         # other classes' best singles forward selection also starts from (``other_firsts``)
MIN_SCORE_GAIN = 25.0      # held-out NLL + BIC penalty improvement over the nominal model
TIME_MIN_PERIODS = 40      # the veto's span held out in time: the serious stage when it holds this many periods
QUANTUM_OVER_SCENARIO = 1.5  # a lattice of speeds this many times the scenario's own quantum is a quantiser to name
MIN_GAP = 0.5              # combined gap (noise units) below which there is no gap to explain (above what the
                           # sensor noise alone leaves on a nominal run: docs/design/gap-diagnosis.md)

#: what a candidate's fit can raise: least_squares' ValueError (residuals not finite at a start, a start
#: outside the bounds; numpy's LinAlgError is a ValueError), the simulator's FloatingPointError (the model
#: diverged) and other ArithmeticErrors (overflow in exp of a log-space parameter), CasADi's RuntimeError
FIT_ERRORS = (ArithmeticError, ValueError, RuntimeError)


def quiet(msg: str) -> None:
    """The default progress sink: say nothing."""


def failure(name: str, step: str, error: BaseException) -> dict:
    """One failed candidate fit, as the report lists it: candidate ``name``, its effect class and form,
    the ``step`` of the diagnosis it failed in, and the error."""
    spec = EFFECTS.get(name)
    return {"name": name, "effect": spec.effect_class if spec else name, "form": spec.form if spec else "",
            "step": step, "error": f"{type(error).__name__}: {error}"}


def fit_candidates(ctx: Context, nom_fit: Fit, cands, failed: list, say=quiet) -> list[Fit]:
    """Every candidate fitted alone on the training blocks.  A fit that fails is kept in the ranking
    with the nominal model's prediction (it removes nothing) and ``note`` "fit failed: ...", and is
    appended to ``failed``."""
    nominal = {k: nom_fit.pred[k] for k in SIGNALS}
    fits = []
    for cand in cands:
        say(f"fitting candidate {cand.name}")
        try:
            fit = cand.fit(ctx, nom_fit)
        except FIT_ERRORS as e:
            failed.append(failure(cand.name, "alone", e))
            fit = Fit(cand.name, {}, 1, dict(nominal), dict(ctx.sigma_nom), note=f"fit failed: {e}")
        fits.append(fit)
    return fits


def fit_rail(ctx: Context, nom_fit: Fit, base: dict, failed: list, say=quiet) -> tuple[Fit | None, dict | None]:
    """The nuisance: the rail's fault curve scaled in mu and in creep, fitted as a candidate; (fit, its
    ranking row), or (None, None) when the fit fails (appended to ``failed``)."""
    say("fitting the nuisance: the rail's fault curve (scale in mu and creep)")
    try:
        rail_fit = RAIL.fit(ctx, nom_fit)
    except FIT_ERRORS as e:
        failed.append(failure(RAIL.name, "nuisance", e))
        say(f"rail curve fit failed: {e}")
        return None, None
    return rail_fit, entry(ctx, rail_fit, base)


def quantiser(ctx: Context, nom_fit: Fit, cands, failed: list, say=quiet) -> tuple[dict | None, Fit | None]:
    """The quantisation candidate's fit when the measured speeds sit on a lattice (coherence > 0.9, so
    never on continuous readings) at least ``QUANTUM_OVER_SCENARIO`` times the scenario's own quantum:
    ({"params", "note"}, the fit: the augmented replay of a quantiser-only answer); else (None, None)
    (and when the candidate is not in ``cands``, or its fit fails: appended to ``failed``, and it is
    fitted again with the rest)."""
    cand = next((c for c in cands if c.name == "sensor_quantisation"), None)
    if cand is None:
        return None, None
    say("fitting candidate sensor_quantisation (judged apart: it changes the noise)")
    try:
        fit = cand.fit(ctx, nom_fit)
    except FIT_ERRORS as e:
        failed.append(failure(cand.name, "quantiser (judged apart)", e))
        return None, None
    sens = ctx.scenario.sensors
    own = {"motor_quantum_rad_s": sens.motor_speed_quantum_rad_s, "train_quantum_ms": sens.train_speed_quantum_ms}
    if not any(q > 0 and q >= QUANTUM_OVER_SCENARIO * own.get(k, 0.0) for k, q in fit.params.items()):
        return None, None
    return {"params": dict(fit.params), "note": fit.note}, fit


@dataclass
class Row:
    """One fitted candidate (or the rail nuisance, or a pair forward selection built) as the answer
    judges it: its class and form, the candidate fitted, its parameters (``k`` fitted), the held-out
    score gain over the nominal model, the share of the held-out gap it removes (``held_out_shrink``;
    ``share`` clipped to 0-1) and the gap it leaves (noise units; ``held_out_gap_own_floor``: in its own
    noise floor's), which parameters sit at a bound and their intervals, its fit's note, and per
    signal its held-out RMSE and gap.  A pair's row also holds its first effect's parameters, form and
    candidate (``first_*``; None for a single).  ``to_json`` is what ``which.ranking`` lists."""

    effect: str
    form: str
    candidate: str
    params: dict
    k: int
    score_gain: float
    held_out_shrink: float
    held_out_gap: float
    held_out_gap_own_floor: float = math.nan
    at_bound: dict = field(default_factory=dict)
    param_ci: dict = field(default_factory=dict)
    note: str = ""
    per_signal: dict = field(default_factory=dict)
    first_params: dict | None = None
    first_form: str | None = None
    first_candidate: str | None = None

    @property
    def share(self) -> float:
        return min(max(self.held_out_shrink, 0.0), 1.0)

    def brief(self) -> dict:
        return {"candidate": self.candidate, "params": self.params, "score_gain": self.score_gain,
                "held_out_shrink": self.held_out_shrink, "held_out_gap": self.held_out_gap}

    def to_json(self) -> dict:
        out = {"effect": self.effect, "form": self.form, "candidate": self.candidate, "params": self.params,
               "k": self.k, "score_gain": self.score_gain, "held_out_shrink": self.held_out_shrink,
               "share": self.share, "held_out_gap": self.held_out_gap,
               "held_out_gap_own_floor": self.held_out_gap_own_floor, "at_bound": self.at_bound,
               "param_ci": self.param_ci, "note": self.note, "per_signal": self.per_signal}
        for k in ("first_params", "first_form", "first_candidate"):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        return out


def entry(ctx: Context, fit: Fit, base: dict) -> Row:
    """One ranking row: held-out score gain and shrink against the nominal model, form, interval."""
    sc_ = score(ctx, fit)
    shrink = 1 - sc_["gap"] / base["gap"] if base["gap"] > 0 else 0.0
    spec = EFFECTS.get(fit.name)
    return Row(spec.effect_class if spec else fit.name, spec.form if spec else "", fit.name, fit.params, fit.k,
               base["score"] - sc_["score"], shrink, sc_["gap"], sc_["gap_own_floor"], fit.extra.get("at_bound", {}),
               fit.extra.get("param_ci", {}), fit.note, sc_["per_signal"])


def off_vehicle(row: Row) -> list[str]:
    """The fitted parameters of ``row`` (a pair's first effect's too) outside the range a vehicle allows
    (``EffectSpec.plausible``), as "name=value (lo-hi unit)": a fit that explains the log only with,
    say, a bogie pivot a few centimetres above the rail stands for some other change of the curve's
    shape, not for this effect (issue 51), and weighs against its candidate."""
    out = []
    for cand, params in ((row.candidate, row.params), (row.first_candidate, row.first_params or {})):
        spec = EFFECTS.get(cand or "")
        for k, (lo, hi) in (spec.plausible if spec else {}).items():
            v = params.get(k)
            if v is not None and not lo <= v <= hi:
                out.append(f"{k}={v:.3g} ({lo:g}-{hi:g} {spec.units.get(k, '')})".replace(" )", ")"))
    return out


def beats(a: dict, b: dict) -> bool:
    """``a`` explains the held-out data better than ``b`` by the margin: a better held-out score by
    MIN_MARGIN and a remaining gap at most MARGIN_GAP_RATIO of ``b``'s (unless ``b``'s is already
    within the noise: then the score alone decides)."""
    if b.score_gain + MIN_MARGIN > a.score_gain:
        return False
    return a.held_out_gap <= MARGIN_GAP_RATIO * b.held_out_gap or b.held_out_gap <= NOISE_GAP


def beats_on_top(a: dict, b: dict, first: dict) -> bool:
    """Second effect ``a`` beats second effect ``b`` on top of ``first``: a better held-out score by
    MIN_MARGIN, and either it leaves at most MARGIN_GAP_RATIO of what ``b`` leaves (``beats``' rule)
    or it removes at least 1 / MARGIN_GAP_RATIO times as much of the gap ``first`` left (the margin
    judged on what is left to explain: the first rule is out of reach of a right second effect when
    its form differs from the truth's and leaves a remainder of its own; the second alone is out of
    reach of a right second that removes everything when ``b`` removes more than half)."""
    if b.score_gain + MIN_MARGIN > a.score_gain:
        return False
    left = first.held_out_gap
    return (a.held_out_gap <= MARGIN_GAP_RATIO * b.held_out_gap
            or MARGIN_GAP_RATIO * (left - a.held_out_gap) >= left - b.held_out_gap)


def explanations(ranking, rail):
    """The best row of each class (the ranking is sorted by score gain) and the rail nuisance's row
    (``effect`` "rail_curve"): the explanations an answer is judged among."""
    out, seen = [], set()
    for r in ranking:
        if r.effect not in seen:
            seen.add(r.effect)
            out.append(r)
    if rail is not None:
        out.append(rail)
    return sorted(out, key=lambda r: -r.score_gain)


def material(row) -> bool:
    """``row`` removes at least ``MIN_SHRINK`` of the held-out gap and gains ``MIN_SCORE_GAIN``."""
    return row is not None and row.held_out_shrink >= MIN_SHRINK and row.score_gain > MIN_SCORE_GAIN


def within_noise(row) -> bool:
    """``row`` is material and leaves the held-out gap within the noise (``NOISE_GAP`` noise units, the
    level ``beats`` already treats as "within the noise": below it only the score tells models apart):
    nothing is named on top of such an explanation."""
    return material(row) and row.held_out_gap <= NOISE_GAP


def beats_strictly(a: dict, b: dict) -> bool:
    """``beats`` without its noise exemption: a better held-out score by MIN_MARGIN *and* a remaining gap
    at most MARGIN_GAP_RATIO of ``b``'s (how an effect must beat a nuisance that is within the noise)."""
    return b.score_gain + MIN_MARGIN <= a.score_gain and a.held_out_gap <= MARGIN_GAP_RATIO * b.held_out_gap


def profile_gain(a: dict, b: dict) -> float:
    """How much better ``a`` explains the held-out data than ``b`` when the noise level is not taken
    from the noise floor but estimated from each model's own residuals: the Gaussian likelihood ratio
    with the variance profiled out, on the -2 log L scale of ``score``,

        sum_s n_s ln(MSE_b,s / MSE_a,s)

    (no penalty for parameters: they were not fitted on these samples).  Where the residuals are far
    above the noise floor (a model that forecasts badly) ``score`` counts a tiny relative improvement
    as thousands; this counts it by the share of the residual removed."""
    per_a, per_b = a.per_signal, b.per_signal
    return sum(per_a[s]["n"] * 2 * math.log(per_b[s]["rmse"] / per_a[s]["rmse"]) for s in per_a
               if per_a[s]["rmse"] and per_b[s]["rmse"])


def beats_in_time(a: dict, b: dict) -> bool:
    """How a pair must beat a single explanation on data held out in time (``time_veto``): a better
    score by ``MIN_MARGIN`` *and* a better ``profile_gain`` by ``MIN_MARGIN``.  Not ``beats_strictly``'s
    halving of the gap: fitted on the span before the stage it forecasts, a right first effect
    extrapolates with an error of its own that no second effect removes (a true delay under a load
    transfer leaves most of the first's gap there), while a second effect fitted into a wrong first's
    remainder removes next to none of it; where that remainder is large the score with the noise floor
    counts next to none as thousands, the profiled score does not (docs/design/gap-diagnosis.md)."""
    return b.score_gain + MIN_MARGIN <= a.score_gain and profile_gain(a, b) >= MIN_MARGIN


def label(row) -> str:
    """An explanation as the verdict names it: its class and form, or "the rail curve"."""
    return "the rail curve" if row.effect == "rail_curve" else f"{row.effect} ({row.form})"


@dataclass
class Verdict:
    """The answer, written once and read by the terminal summary, report.md and ``--json`` alike
    (``which``: ``named``, ``named_set``, ``verdict`` = ``sentence``, ``confidence`` = ``grade``; ``shrink``:
    ``how_far``).  ``grade``: "confident", "tentative", "not_separable", "nuisance" or "none"; ``named``:
    the effect named first (``NONE`` when none is), ``named_set`` every effect named; ``alternatives``:
    the explanations a "not_separable" answer lists (ranking rows, the rail's included, best score
    first); ``nuisances``: the rail's fitted curve; ``how_far``: the explanation whose held-out shrink
    HOW FAR reports (``HowFar``); ``separate_by``: where a "not_separable" answer's first two
    explanations differ most (``where.separation``)."""

    grade: str
    sentence: str
    named: str = NONE
    named_set: list = field(default_factory=list)
    alternatives: list = field(default_factory=list)
    nuisances: list = field(default_factory=list)
    how_far: "HowFar | None" = None
    separate_by: list = field(default_factory=list)

    def also(self, clause: str) -> None:
        """One more clause at the end of the sentence."""
        self.sentence = f"{self.sentence}; {clause}"


@dataclass
class HowFar:
    """HOW FAR: the explanation whose held-out shrink is reported (``label``: a class, a pair "a + b", or
    "sensor_quantisation"), whether it is the answer's (``named``: else it is only reported beside an
    answer that names nothing), its held-out shrink (0-1) and per signal the RMSE and gap it leaves."""

    label: str
    named: bool
    held_out_shrink: float
    per_signal: dict

    def said(self) -> str:
        """What the shrink is of, as the summary and report.md say it."""
        if self.label == "rail_curve":
            return "the rail curve, the nuisance the answer names"
        return self.label if self.named else f"{self.label}, the best single, not named"


def judge(base, ranking, rail, gap_present) -> Verdict:
    """The answer from the single candidates' ranking and the rail nuisance (see the module
    docstring); its ``how_far`` is set by the caller."""
    best = ranking[0]
    runner = next((r for r in ranking[1:] if r.effect != best.effect), None)   # another class's best
    nuisances = []
    if rail is not None:
        p = rail.params
        nuisances.append({"name": "rail_curve", "params": p, "score_gain": rail.score_gain,
                          "held_out_shrink": rail.held_out_shrink, "held_out_gap": rail.held_out_gap,
                          "at_bound": rail.at_bound, "param_ci": rail.param_ci,
                          "peak_mu_percent": (p["peak_mu_scale"] - 1) * 100,
                          "peak_creep_percent": (p["creep_scale"] - 1) * 100})
    if not gap_present:
        return Verdict("none", f"no significant gap: held-out residuals are within {base['gap']:.2f} noise units of "
                               f"the sensor noise floor", nuisances=nuisances)
    desc = (f"{best.effect} ({best.form}) removes {best.share * 100:.0f} % of the held-out gap, leaves "
            f"{best.held_out_gap:.2f} noise units, fitted "
            + ", ".join(f"{k}={v:.4g}" for k, v in best.params.items()))
    bounded = [k for k, v in best.at_bound.items() if v]
    bound_note = f" (fit at its bound: {', '.join(bounded)})" if bounded else ""
    # a fit with every parameter at a bound is pinned (the effect vanishes or runs off its range): no
    # name; one parameter of several at a bound (viscous loss 0 beside a Coulomb loss) is only said
    pinned = bool(bounded) and len(bounded) == len(best.at_bound)
    rail_desc = ""
    if rail is not None:
        n = nuisances[0]
        rail_desc = (f"peak mu {n['peak_mu_percent']:+.1f} %, peak creep {n['peak_creep_percent']:+.1f} % removes "
                     f"{rail.share * 100:.0f} % of the held-out gap, leaves {rail.held_out_gap:.2f} noise units")
    # the explanations that matter, best held-out score first; the top one and every other one it does
    # not beat by the margin.  Once the rail curve leaves the gap within the noise, an effect must beat
    # it on both counts (score and half its gap: ``beats_strictly``), not by the score alone
    cands = [r for r in explanations(ranking, rail) if material(r)]
    quiet_rail = within_noise(rail)
    if quiet_rail:
        cands = [r for r in cands if r is rail or beats_strictly(r, rail)] + \
            [r for r in cands if r is not rail and not beats_strictly(r, rail) and not beats(rail, r)]
        cands.sort(key=lambda r: -r.score_gain)
        if cands and cands[0] is not rail and not beats_strictly(cands[0], rail):
            cands.remove(rail)
            cands.insert(0, rail)          # within the noise, the rail stands first unless strictly beaten
    if cands:
        top = cands[0]
        listed = [top] + [r for r in cands[1:] if r.effect != top.effect and not beats(top, r)]
        if len(listed) > 1:
            names = " or ".join(label(r) for r in listed)
            return Verdict("not_separable", f"{names}: not separable in this log ("
                           + "; ".join(f"{label(r)} removes {r.share * 100:.0f} %, leaves "
                                       f"{r.held_out_gap:.2f} noise units" for r in listed) + ")",
                           alternatives=listed, nuisances=nuisances)
        if top is rail and quiet_rail:
            return Verdict("nuisance", f"the rail's curve differs: {rail_desc} (within the noise: nothing more is "
                                       f"named), more than any effect (best: {desc})", nuisances=nuisances)
        if top is rail:
            # the best explanation, by the margin, yet not the whole story: "the rail's curve differs" would
            # claim what the log does not show (a constant-power limit is mimicked this way), so no grade
            # above "none" (docs/design/gap-diagnosis.md, issue 35)
            return Verdict("none", f"none of the candidates explains the whole gap: the rail's curve beats every "
                                   f"effect by the margin ({rail_desc}; the best effect: {desc}) but leaves more than "
                                   f"the noise ({NOISE_GAP:g} noise units): what differs is not only the rail's curve",
                           nuisances=nuisances)
    is_material = material(best)
    over_runner = runner is None or beats(best, runner)
    over_rail = rail is None or beats(best, rail)
    off = off_vehicle(best)
    if is_material and over_runner and over_rail and not pinned and not off:
        return Verdict("confident", f"{best.effect} explains the gap: {desc}{bound_note}", best.effect, [best.effect],
                       nuisances=nuisances)
    if is_material:
        why = "its fit sits at a bound" if pinned else (
            f"its fitted {', '.join(off)} lies outside what a vehicle allows" if off else
            f"it does not beat {runner.effect} ({runner.share * 100:.0f} %) by the margin" if not over_runner
            else "it does not beat the rail-curve nuisance by the margin")
        return Verdict("tentative", f"none named with confidence: most likely {desc}{bound_note}; {why}",
                       nuisances=nuisances)
    return Verdict("none", f"none of the candidates: the best, {desc}, removes less than "
                           f"{MIN_SHRINK * 100:.0f} %{bound_note}", nuisances=nuisances)


# -- forward selection -----------------------------------------------------------------------------
def forward(ctx: Context, nom_fit: Fit, base: dict, first: Fit, first_row: Row, rail_fit, ranking, exclude,
            failed: list, say=quiet, alone: dict | None = None) -> dict | None:
    """Second step of forward selection: every form of every other class fitted on top of the first
    (its parameters held), judged on held-out data against the first alone.  Sensor-level pairs are not
    tried (a delay on a delay is one delay).  Accepted when the best second effect removes at least
    ``FORWARD_MIN_REMAINDER`` of what the first left, gains ``MIN_MARGIN`` in held-out score, beats the
    best second effect of another class by the margin (``beats_on_top``) and its fit is not pinned at
    its bounds; and, as a single effect must (issue 35), the pair beats every class's best single
    candidate by the margin (``beats``), no parameter of it sits at a bound of its range but a zero
    floor (``implausible``), and the pair or the rail curve with the same second effect beats the rail
    curve alone.  The pair is then compared with the rail curve plus the same second effect (``pair_vs_rail``)
    and, when the first alone did not beat another class's best by the margin, with that class's best
    plus the same second effect (``pair_vs_runner``, read by ``rejudge``), and, last
    (it costs fits), the pair named must win on data held out in time (``time_veto``: fitted without the
    serious stage, judged on it) and, a plant first, beat the first alone fitted again from where its fit
    there landed (``Forward.first_again``).  ``rejected_because`` says which test failed;
    ``own_tests_passed``, that the second passed its own tests and the pair was turned away only against
    other explanations (``pair_explanation`` lists it then).  ``exclude``: candidates
    not to offer; ``alone``: the single candidates' fits by name (the rival class's best is built on, not
    fitted again); a fit that fails at any step is appended to ``failed`` (a second effect whose fit on
    top fails is not ranked; a failed joint fit or refit keeps the fit it would replace).

    The steps (``Forward``'s methods, in order): ``seconds`` (every second on top of the first, pairs
    of a plant and a sensor form fitted together), ``descend`` (the best second and the first refitted
    on top of each other), ``own_tests`` and ``answer`` (the second's own tests, the pair against every
    single), ``against_rail``, ``against_runner``, ``in_time`` (with ``first_again``)."""
    if first.name == "sensor_quantisation":
        return None
    fw = Forward(ctx, nom_fit, base, first, first_row, {c.name: c for c in candidates(ctx.scenario, exclude)},
                 failed, say)
    rows, fits2, joint = fw.seconds(ranking)
    if not rows:
        return None
    runner = next((r for r in rows[1:] if r.effect != rows[0].effect), None)   # another class's best
    second = fw.descend(rows[0], fits2[rows[0].candidate], joint)
    out = fw.answer(second, rows, *fw.own_tests(second, runner, ranking))
    if out["accepted"] and rail_fit is not None:
        fw.against_rail(second, rail_fit, out)
    else:
        out["pair_vs_rail"] = "pair"
    fw.against_runner(second, ranking, alone, out)
    if out["accepted"]:
        fw.in_time(rail_fit, out)
    return out


@dataclass
class Forward:
    """What every step of one forward selection (``forward``) reads: the context, the nominal fit and
    score (``base``), the first effect's fit and row, the candidates offered by name, the caller's
    list of failed fits and its progress line."""

    ctx: Context
    nom_fit: Fit
    base: dict
    first: Fit
    first_row: Row
    by_name: dict
    failed: list
    say: object = quiet

    def seconds(self, ranking) -> tuple[list, dict, set]:
        """(rows best first, their fits by candidate, the seconds fitted together with the first): every
        form of every other class on top of the first.  A plant effect fitted alone absorbs part of a
        sensor delay (a lag looks like a delay), so the delay on top finds little of it: a sensor second
        on a plant first is fitted together with the first class's best ``FORWARD_JOINT`` forms (the
        form best alone need not be best in a pair); and a sensor form fitted alone absorbs part of a
        lag: on a sensor first the best ``FORWARD_JOINT`` plant seconds are fitted together with it."""
        ctx, first, by_name, base = self.ctx, self.first, self.by_name, self.base
        sensor_first = "plant" not in first.extra
        ctx2 = ctx.on_top_of(first)
        on_first = pseudo(first, self.nom_fit)
        rows, fits2, joint = [], {}, set()
        first_cand = by_name.get(first.name)
        first_forms = [r for r in ranking if r.effect == self.first_row.effect     # (a form whose fit failed
                       and isinstance(by_name.get(r.candidate), PlantCandidate)    # alone has no parameters)
                       and not r.note.startswith("fit failed")][:FORWARD_JOINT]
        for cand in by_name.values():
            if EFFECTS[cand.name].effect_class == self.first_row.effect or \
                    cand.name == "torque_lag" and ctx.data.torque_cmd_nm.std() < 1e-9:
                continue
            if sensor_first and not isinstance(cand, PlantCandidate):
                continue
            self.say(f"forward selection: {cand.name} on top of {first.name}")
            try:
                f2 = cand.fit(ctx2, on_first)
            except FIT_ERRORS as e:
                self.failed.append(failure(cand.name, f"on top of {first.name}", e))
                continue
            row = entry(ctx, f2, base)
            if isinstance(first_cand, PlantCandidate) and isinstance(cand, SensorDelayCandidate):
                for r1 in first_forms:
                    c1 = by_name[r1.candidate]
                    try:
                        self.say(f"forward selection: {c1.name} and {cand.name} fitted together")
                        jf = fit_pair(ctx, c1, cand, r1.params, f2.extra[cand.ARGUMENT[cand.form]],
                                      f2.extra["x0"])
                        jrow = replace(entry(ctx, jf, base), first_params=jf.extra["plant_params"],
                                       first_form=r1.form, first_candidate=c1.name)
                        # the better pair: a plausible one (no parameter off its range) before the best score
                        # (a form that runs off its range to score well would be rejected as implausible,
                        # where another form of the same class fits the pair within its range)
                        now = by_name.get(row.first_candidate or first.name, first_cand)
                        if (not implausible(jrow, [c1, cand]), jrow.score_gain) > \
                                (not implausible(row, [now, cand]), row.score_gain):
                            row = jrow
                            joint.add(cand.name)
                    except FIT_ERRORS as e:       # keep the greedy fit
                        self.failed.append(failure(cand.name, f"together with {c1.name}", e))
            fits2[cand.name] = f2
            rows.append(row)
        rows.sort(key=lambda r: -r.score_gain)
        if rows and isinstance(first_cand, SensorDelayCandidate):
            for i, row in enumerate(rows[:FORWARD_JOINT]):
                cand = by_name[row.candidate]
                if not isinstance(cand, PlantCandidate):
                    continue
                try:
                    self.say(f"forward selection: {cand.name} and {first.name} fitted together")
                    f2 = fits2[cand.name]
                    jf = fit_pair(ctx, cand, first_cand, f2.params,
                                  first.extra[first_cand.ARGUMENT[first_cand.form]], f2.extra["x0"])
                    jrow = entry(ctx, plant_side(jf, cand), base)
                    if jrow.score_gain > row.score_gain:
                        rows[i] = replace(jrow, first_params=jf.params)
                        joint.add(cand.name)
                except FIT_ERRORS as e:           # keep the greedy fit
                    self.failed.append(failure(cand.name, f"together with {first.name}", e))
            rows.sort(key=lambda r: -r.score_gain)
        return rows, fits2, joint

    def descend(self, second: Row, f2: Fit, joint: set) -> Row:
        """The best second after one round of coordinate descent: the first was fitted alone and absorbed
        part of the second, so each is refitted on top of the other, the refit kept only if it scores
        better; then a plant effect and a sensor form are fitted together from where the pair stands.
        A second already fitted together with the first (``joint``) is done."""
        if second.candidate in joint:
            return second
        ctx, first, by_name, base, nom_fit = self.ctx, self.first, self.by_name, self.base, self.nom_fit
        f1_now, f2_now = first, f2           # the pair as it stands
        refit, under = first.name, f2.name
        try:
            self.say(f"forward selection: refitting {first.name} on top of {f2.name}, then back")
            f1b = by_name[first.name].fit(ctx.on_top_of(f2), pseudo(f2, nom_fit))
            refit, under = f2.name, first.name
            f2b = by_name[f2.name].fit(ctx.on_top_of(f1b), pseudo(f1b, nom_fit))
            row = entry(ctx, f2b, base)
            if row.score_gain > second.score_gain:
                second = row
                second.first_params = f1b.params
                f1_now, f2_now = f1b, f2b
        except FIT_ERRORS as e:               # keep the greedy pair
            self.failed.append(failure(refit, f"refit on top of {under}", e))
        c1, c2 = by_name[first.name], by_name[second.candidate]
        plant_c, sensor_c, plant_f, sensor_f = (c1, c2, f1_now, f2_now) if isinstance(c1, PlantCandidate) \
            else (c2, c1, f2_now, f1_now)
        try:
            if isinstance(plant_c, PlantCandidate) and isinstance(sensor_c, SensorDelayCandidate):
                self.say(f"forward selection: {plant_c.name} and {sensor_c.name} fitted together")
                jf = fit_pair(ctx, plant_c, sensor_c, plant_f.params,
                              sensor_f.extra[SensorDelayCandidate.ARGUMENT[sensor_c.form]], f2_now.extra["x0"])
                if c2.name == sensor_c.name:          # the second is the sensor form: the row as it is
                    row, first_params = entry(ctx, jf, base), jf.extra["plant_params"]
                else:                                 # the second is the plant effect: name the row after it
                    row, first_params = entry(ctx, plant_side(jf, plant_c), base), jf.params
                if row.score_gain > second.score_gain:
                    second = row
                    second.first_params = first_params
        except FIT_ERRORS as e:               # keep the pair as it is
            self.failed.append(failure(plant_c.name, f"together with {sensor_c.name}", e))
        return second

    def own_tests(self, second: Row, runner: Row | None, ranking) -> tuple[float, list, list]:
        """(the share of what the first left that the second removes, the second's own tests failed, every
        reason to turn the pair away).  Its own tests: does it add to the first, is it this class, is
        its fit plausible; then the pair must earn its place as a single effect would, beating every
        class's best single candidate by the margin (``beats``), not only the first alone.  A pair that
        passes its own tests and fails only against the others is one more explanation within the
        margin (``pair_explanation``)."""
        first_row = self.first_row
        removed = 1 - second.held_out_gap / first_row.held_out_gap if first_row.held_out_gap > 0 else 0.0
        bounded = [k for k, v in second.at_bound.items() if v]
        bounded = bounded if len(bounded) == len(second.at_bound) else []      # pinned, as in ``judge``
        off_range = implausible(second, [self.by_name[n] for n in (second.candidate, self.first.name)
                                         if n in self.by_name])
        unbeaten = [r.candidate for r in explanations(ranking, None) if not beats(second, r)]
        own = [w for w, bad in (
            (f"it gains less than {MIN_MARGIN:g} in held-out score over {first_row.effect} alone",
             second.score_gain - first_row.score_gain < MIN_MARGIN),
            (f"it removes less than {FORWARD_MIN_REMAINDER * 100:.0f} % of what {first_row.effect} left",
             removed < FORWARD_MIN_REMAINDER),
            (f"it does not beat {runner.effect if runner else ''} on top by the margin",
             runner is not None and not beats_on_top(second, runner, first_row)),
            ("its fit is pinned at its bounds", bool(bounded)),
            (f"parameters at a bound of their range: {', '.join(off_range)}", bool(off_range)),
            (f"fitted outside what a vehicle allows: {', '.join(off_vehicle(second))}", bool(off_vehicle(second))),
            (f"the pair removes less than {MIN_SHRINK * 100:.0f} %", second.held_out_shrink < MIN_SHRINK),
        ) if bad]
        why = own + ([f"the pair does not beat the single candidate(s) {', '.join(unbeaten)} by the margin"]
                     if unbeaten else [])
        return removed, own, why

    def answer(self, second: Row, rows: list, removed: float, own: list, why: list) -> dict:
        """The pair as ``which.forward`` records it (accepted when no test failed)."""
        first, first_row = self.first, self.first_row
        return {"first": first_row.effect,
                "first_form": second.first_form if second.first_form is not None else first_row.form,
                "first_candidate": second.first_candidate if second.first_candidate is not None else first.name,
                "second_candidate": second.candidate,
                "second": second.effect,
                "second_form": second.form,
                "second_params": second.params,
                "first_params": second.first_params if second.first_params is not None else first.params,
                "pair_held_out_shrink": second.held_out_shrink,
                "second_removes_of_remainder": removed, "accepted": not why, "rejected_because": why,
                "own_tests_passed": not own, "pair_score_gain": second.score_gain,
                "pair_held_out_gap": second.held_out_gap, "pair_per_signal": second.per_signal,
                "ranking": [{k: r.to_json()[k] for k in ("effect", "form", "params", "score_gain",
                                                         "held_out_shrink", "held_out_gap", "at_bound")}
                            for r in rows]}

    def against_rail(self, second: Row, rail_fit: Fit, out: dict) -> None:
        """Is the first effect the rail in disguise?  The rail curve plus the same second effect
        (``out["pair_vs_rail"]``); and the pair, or the rail with the same second effect, must beat the
        rail alone by the margin a single effect needs."""
        ctx, base = self.ctx, self.base
        cand = self.by_name[second.candidate]
        try:
            r2 = cand.fit(ctx.on_top_of(rail_fit), Fit("rail_curve", rail_fit.params, 0, rail_fit.pred,
                                                        dict(ctx.sigma_nom), extra={
                                                            "x0": rail_fit.extra["x0"],
                                                            "plant_motor": rail_fit.extra["plant_motor"],
                                                            "plant_train": rail_fit.extra["plant_train"]}))
            row = entry(ctx, r2, base)
            out["rail_pair"] = {"held_out_shrink": row.held_out_shrink, "score_gain": row.score_gain,
                                "held_out_gap": row.held_out_gap}
            out["pair_vs_rail"] = ("pair" if beats(second, row) else
                                   "rail" if beats(row, second) else "not_separable")
            rail_row = entry(ctx, rail_fit, base)
            if not (beats(second, rail_row) or beats(row, rail_row)):
                out["accepted"] = False
                out["rejected_because"] = ["neither the pair nor the rail curve with the same second effect beats "
                                           "the rail curve alone by the margin"]
        except FIT_ERRORS as e:               # the pair stands untested against the rail
            self.failed.append(failure(cand.name, "on top of the rail curve", e))
            out["pair_vs_rail"] = "pair"

    def against_runner(self, second: Row, ranking, alone: dict | None, out: dict) -> None:
        """When the first was only "most likely" alone (another class within the margin of it): is it the
        first of the pair, or is that class?  The other class's best with the same second effect on top
        (``out["pair_vs_runner"]``, read by ``rejudge``)."""
        first_row = self.first_row
        runner1 = next((r for r in ranking if r.effect != first_row.effect), None)   # as ``rejudge``'s
        f_other = (alone or {}).get(runner1.candidate) if runner1 is not None else None
        if not (out["accepted"] and f_other is not None and not beats(first_row, runner1)
                and runner1.effect != second.effect):
            return
        cand = self.by_name[second.candidate]
        try:
            r2 = entry(self.ctx, cand.fit(self.ctx.on_top_of(f_other), pseudo(f_other, self.nom_fit)), self.base)
            out["runner_pair"] = {"first": runner1.candidate, "held_out_shrink": r2.held_out_shrink,
                                  "score_gain": r2.score_gain, "held_out_gap": r2.held_out_gap}
            out["pair_vs_runner"] = "pair" if beats(second, r2) else "not_separable"
        except FIT_ERRORS as e:               # the first stays "most likely"
            self.failed.append(failure(cand.name, f"on top of {runner1.candidate}", e))

    def in_time(self, rail_fit, out: dict) -> None:
        """Last (it costs fits): the pair named must win on data held out in time, fitted without the
        last stage and judged on it (the pair named: the rail curve with the second when that explains
        it better than the first with it)."""
        pair = ("rail_curve" if out["pair_vs_rail"] == "rail" else out["first_candidate"], out["second_candidate"])
        veto = time_veto(self.ctx, self.first.name, pair, rail_fit is not None, self.failed, self.say)
        early = veto.pop("first_fit", None) if veto is not None else None
        out["held_out_in_time"] = veto
        if veto is not None and not veto["pair_wins"]:
            out["accepted"] = False
            out["rejected_because"] = [veto["why"]]
        elif veto is not None:
            self.first_again(veto, early, out)

    def first_again(self, veto: dict, early: Fit | None, out: dict) -> None:
        """After the veto in time, when the first is a plant effect: the first alone fitted again on the
        analysis window from where its fit on the data before the held-out stage landed (its parameters
        and initial state: ``early``, ``time_veto``'s ``first_fit``; one local fit, no scan).  A fit of
        the first that stopped in a poor basin leaves a remainder a second effect can take half of (a second-order
        contact lag at 9.25 Hz fitted 13.5 Hz alone, a running resistance accepted on top: issue 51);
        fitted from another start the first alone may explain it.  The pair must beat that fit by the
        margin (``beats``), as it must beat every single candidate (``own_tests``): when that fit scores
        better than the first's and the pair does not beat it, the pair is turned away
        (``out["first_again"]``: its parameters, score gain, shrink and gap)."""
        cand = self.by_name.get(self.first.name)
        if not isinstance(cand, PlantCandidate) or early is None:
            return
        self.say(f"forward selection: {cand.name} alone again, from its fit before {veto['held_out']}")
        try:
            row = entry(self.ctx, cand.fit(self.ctx, self.nom_fit, starts=[(early.params, early.extra["x0"])]),
                        self.base)
        except FIT_ERRORS as e:               # the pair stands as the veto left it
            self.failed.append(failure(cand.name, f"alone again, from its fit before {veto['held_out']}", e))
            return
        out["first_again"] = {"params": row.params, "score_gain": row.score_gain,
                              "held_out_shrink": row.held_out_shrink, "held_out_gap": row.held_out_gap}
        if row.score_gain > self.first_row.score_gain and not beats(pair_row(out), row):
            out["accepted"] = False
            out["rejected_because"] = [
                f"{self.first_row.effect} alone, fitted again from where its fit before {veto['held_out']} landed ("
                + ", ".join(f"{k}={v:.4g}" for k, v in row.params.items())
                + f"), removes {row.share * 100:.0f} % and leaves {row.held_out_gap:.2f} noise units: the pair "
                  f"does not beat it by the margin"]


def other_firsts(ranking, best) -> list[dict]:
    """Forward selection's other starts, tried when the pair built on the best single candidate is not
    accepted: the best single of each other class that the best does not beat by the margin (``beats``)
    and that would itself start forward selection (it removes ``FORWARD_MIN_SHARE`` and leaves more than
    the noise), best score first, at most ``FORWARD_FIRSTS``.  Greedy selection builds only on the best
    single, and the best single need not be the first of the true pair: where a form stands for a
    held-out one (a delay for a low-pass), another class may explain as much alone and take what would
    be the second's evidence, so the true first is among those the best did not beat
    (docs/design/gap-diagnosis.md)."""
    return [r for r in explanations(ranking, None)
            if r.effect != best.effect and not beats(best, r)
            and r.held_out_shrink >= FORWARD_MIN_SHARE and r.held_out_gap > NOISE_GAP][:FORWARD_FIRSTS]


def pair_row(fw: dict) -> Row:
    """A pair forward selection found, as a row ``beats`` compares (its score gain and remaining gap)."""
    return Row("pair", "", "", {}, 0, fw["pair_score_gain"], math.nan, fw["pair_held_out_gap"])


def choose_pair(tried: list) -> tuple:
    """(first_row, fw, rivals) among forward selections from several firsts (``tried``: (first's ranking
    row, ``forward``'s answer) pairs, the best single's first): the accepted pair with the best held-out
    score, and the other accepted pairs it does not beat by the margin (``beats``), which make the
    answer "not_separable"; (None, None, []) when none was accepted."""
    won = sorted((t for t in tried if t[1]["accepted"]), key=lambda t: -t[1]["pair_score_gain"])
    if not won:
        return None, None, []
    row, fw = won[0]
    return row, fw, [f for _, f in won[1:] if not beats(pair_row(fw), pair_row(f))]


def time_split(ctx: Context):
    """(train, held, what) for the veto from data held out in time: ``held`` the serious stage of the
    analysis window (the last stage: a model fitted on what came before must forecast it) when it holds
    at least ``TIME_MIN_PERIODS`` periods, else the later half of the window after the fault; ``train``
    every period of the window before it.  None when the window holds too little after the fault."""
    sc, d = ctx.scenario, ctx.data
    st = stages(d.t_s, ctx.observer.creep_kmh(d.motor_speed_rad_s, d.train_speed_ms), sc.run.fault_time_s,
                sc.fault_curve.peak()[0])
    held, what = ctx.window & (st == 2), "the serious stage"
    if held.sum() < TIME_MIN_PERIODS:
        after = np.flatnonzero(ctx.window & (st >= 1))
        if after.size < 2 * TIME_MIN_PERIODS:
            return None
        held, what = ctx.window & (np.arange(d.n) >= after[after.size // 2]), "the later half after the fault"
    train = ctx.window & (np.arange(d.n) < int(np.flatnonzero(held)[0]))
    return train, held, what


def time_veto(ctx: Context, first_name: str, pair: tuple, rail: bool, failed: list, say=quiet) -> dict | None:
    """The veto from data held out in time (issue 35 item 3): the pair ``pair`` = (first, second candidate
    names) fitted again on the analysis window before its last stage (``time_split``: greedy, the second
    on top of the first; a plant effect and a sensor form then fitted together, the better on training
    kept), and judged on that stage against the first effect alone (``first_name``) and the rail curve
    alone (``rail``), fitted the same way.  The pair wins when it beats each there (``beats_in_time``:
    ``MIN_MARGIN`` in score, and ``MIN_MARGIN`` in score with the noise level estimated from the
    residuals): a second effect fitted into a misspecified first's remainder follows the training span,
    not what comes after it.  ``pair[0]`` may be "rail_curve" (the rail curve with the second effect).
    None when the window holds too little after the fault (no veto); a pair whose fit fails there does
    not win.  ``first_fit``: the first alone as fitted there (None when its fit failed), for
    ``Forward.first_again``."""
    split = time_split(ctx)
    if split is None:
        return None
    train, held, what = split
    ct = ctx.split(train, held)
    by_name = {c.name: c for c in candidates(ctx.scenario)}
    by_name[RAIL.name] = RAIL
    step = f"held out in time ({what})"
    say(f"forward selection: the pair {' and '.join(pair)} fitted without {what}, judged on it")
    nom = fit_nominal(ct)
    base = score(ct, nom)
    fits = {}
    try:
        c1, c2 = by_name[pair[0]], by_name[pair[1]]
        f1 = fits[c1.name] = c1.fit(ct, nom)
        f2 = c2.fit(ct.on_top_of(f1), pseudo(f1, nom))
        plant_c, sensor_c, plant_f, sensor_f = (c1, c2, f1, f2) if isinstance(c1, PlantCandidate) else (c2, c1, f2, f1)
        if isinstance(plant_c, PlantCandidate) and isinstance(sensor_c, SensorDelayCandidate):
            jf = fit_pair(ct, plant_c, sensor_c, plant_f.params,
                          sensor_f.extra[SensorDelayCandidate.ARGUMENT[sensor_c.form]], f2.extra["x0"])
            f2 = jf if jf.train_cost < f2.train_cost else f2
    except FIT_ERRORS as e:
        failed.append(failure(pair[1], f"{step}, on top of {pair[0]}", e))
        return {"held_out": what, "periods": int(held.sum()), "pair_wins": False, "rows": [],
                "why": f"the pair's fit failed on the data before {what}"}
    both = entry(ct, f2, base)
    rows = [dict(both.brief(), explanation="the pair")]
    singles = [(first_name, by_name[first_name])] + ([("rail_curve", RAIL)] if rail else [])
    lost, first_fit = [], None
    for name, cand in singles:
        try:
            f = fits[name] if name in fits else cand.fit(ct, nom)
        except FIT_ERRORS as e:
            failed.append(failure(name, f"{step}, alone", e))
            continue
        if name == first_name:
            first_fit = f
        row = entry(ct, f, base)
        rows.append(dict(row.brief(), explanation=name, pair_profile_gain=profile_gain(both, row)))
        if not beats_in_time(both, row):
            lost.append(name)
    return {"held_out": what, "periods": int(held.sum()), "pair_wins": not lost, "rows": rows, "first_fit": first_fit,
            "why": (f"on data held out in time ({what}, fitted on the window before it) the pair does not beat "
                    f"{', '.join(lost)} alone by the margin (in score, and in score with the noise level "
                    f"estimated from the residuals)") if lost else ""}


def implausible(row: dict, cands) -> list[str]:
    """The parameters of a (pair's) ranking row fitted at a bound of their range, but a zero lower bound
    (an absent term of an additive form, as a viscous loss of 0 beside a Coulomb loss, or no delay): a
    fit that ran off its range is no physically plausible second effect.  ``cands``: the candidates
    whose parameters the row holds (bounds)."""
    values = {**(row.first_params or {}), **row.params}
    out = []
    for k, hit in (row.at_bound or {}).items():
        if not hit:
            continue
        zero_floor = False
        for c in cands:
            if isinstance(c, PlantCandidate) and k in c.fit_params:
                i = c.fit_params.index(k)
                zero_floor = c.lo[i] == 0.0 and values.get(k, 1.0) <= 2e-3 * c.hi[i]
            elif isinstance(c, SensorDelayCandidate) and k == c.param:
                zero_floor = values.get(k, 1.0) <= 1e-3
        if not zero_floor:
            out.append(k)
    return out


def pseudo(fit: Fit, nom_fit: Fit) -> Fit:
    """``fit`` as the 'nominal' another candidate builds on (its plant trajectory and start)."""
    return Fit(fit.name, fit.params, 0, fit.pred, dict(fit.sigma),
               extra={"x0": fit.extra["x0"],
                      "plant_motor": fit.extra.get("plant_motor", nom_fit.extra["plant_motor"]),
                      "plant_train": fit.extra.get("plant_train", nom_fit.extra["plant_train"])})


def rejudge(single: Verdict, best, fw, ranking=()) -> Verdict:
    """The answer once forward selection accepted a second effect (``single``: the answer of the single
    candidates, ``best``: the first effect's row).  A first effect that was only
    "most likely" alone because it did not beat the rail nuisance or another class's best by the
    margin is named with the second when the pair beats the rail curve with the same second effect
    and that class's best with it (``pair_vs_runner``), or that class is the second's: those
    comparisons test the first against its rivals now that the second no longer hides in its
    remainder."""
    first, second = fw["first"], fw["second"]
    pair = (f"{second} ({fw['second_form']}) on top of {first} ({fw['first_form']}) removes "
            f"{fw['second_removes_of_remainder'] * 100:.0f} % "
            f"of what {first} left (together {fw['pair_held_out_shrink'] * 100:.0f} % of the gap), fitted "
            + ", ".join(f"{k}={v:.4g}" for k, v in fw["second_params"].items()))
    def named(sentence, *names):
        return Verdict("confident", sentence, names[0], sorted(names), nuisances=single.nuisances)

    if fw["pair_vs_rail"] == "rail":
        return named(f"{second} explains part of the gap and the rail's curve differs: {pair}; the rail curve with "
                     f"{second} explains it better than {first} with {second}", second)
    if fw["pair_vs_rail"] == "not_separable":
        return named(f"{second} found, and rail or {what(first)}: not separable in this log; {pair}", second)
    runner = next((r for r in ranking if r.effect != best.effect), None)
    runner_settled = runner is None or beats(best, runner) or runner.effect == second \
        or fw.get("pair_vs_runner") == "pair"
    only_the_rail = runner_settled and not any(best.at_bound.values())
    if single.grade == "tentative" and not (only_the_rail and "rail_pair" in fw):
        return named(f"{second} found; {pair}; {first} is only the most likely first effect ({single.sentence})",
                     second)
    return named(f"{first} and {second} explain the gap: {first} ({best.form}) removes {best.share * 100:.0f} % "
                 f"alone; {pair}", first, second)


def pair_label(fw: dict) -> str:
    """A pair forward selection found, as the verdict names it."""
    return f"{fw['first']} ({fw['first_form']}) with {fw['second']} ({fw['second_form']})"


def pair_listed(fw: dict) -> dict:
    """A pair forward selection found, as one explanation a "not_separable" answer lists."""
    return {"explanation": pair_label(fw), "effect": fw["first"], "effects": sorted({fw["first"], fw["second"]}),
            "form": fw["first_form"], "held_out_shrink": fw["pair_held_out_shrink"],
            "held_out_gap": fw["pair_held_out_gap"], "score_gain": fw["pair_score_gain"]}


def pair_explanation(fw: dict | None, listed: list) -> dict | None:
    """The pair forward selection found, as one more explanation of a "not_separable" answer (issue 35
    item 2: every explanation within the margin of the others is listed): when the second passed its own
    tests (it adds to the first, beats the other classes' seconds, fits within its range) and the pair
    was turned away only against other explanations (a single candidate or the rail curve it does not
    beat by the margin, on the held-out blocks or on data held out in time), and the best explanation
    listed does not beat it by the margin.  None otherwise.  ``fw``: ``forward``'s answer; ``listed``:
    the answer's explanations (ranking rows, best first)."""
    if not fw or fw["accepted"] or not fw.get("own_tests_passed") or not listed:
        return None
    if beats(listed[0], pair_row(fw)):
        return None
    return dict(pair_listed(fw), turned_away_because=fw["rejected_because"])


def what(effect: str) -> str:
    return {"load_transfer": "axle load"}.get(effect, effect)


# -- scores ---------------------------------------------------------------------------------------
def score(ctx: Context, fit: Fit) -> dict:
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
        per[s] = {"rmse": math.sqrt(ms), "gap": math.sqrt(g2), "n": int(r.size)}
    m = max(sum(1 for s in SIGNALS if per[s]["rmse"] is not None), 1)
    return {"score": nll + fit.k * math.log(max(n, 2)), "gap": math.sqrt(gap2 / m),
            "gap_own_floor": math.sqrt(own2 / m), "per_signal": per}
