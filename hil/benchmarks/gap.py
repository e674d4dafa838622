"""``hil bench gap``: the blind check of the gap diagnosis, on data its candidates did not generate.

K real runs, each drawn (seeded; the seed is drawn at run time unless given, and printed) as one of:

* ``held_out_form``: one effect in a form of its class other than the class's first (creep
  relaxation and a LuGre-type bristle for ``adhesion_lag``; viscous + Coulomb losses and a gear
  efficiency for ``compliance``; a low-pass and a motor-only delay for ``sensor_delay``; a pitch mode
  for ``load_transfer``), and that form is held out of the candidate list for that case (the
  class's other forms stay): the diagnosis must find the class from forms that are not the truth's;
* ``library_form``: one effect in the candidate's own form (the old, circular check, kept as a
  reference; the parameter error is scored only here, where the forms match; ``adhesion_lag2``, the
  second-order contact lag, is a form of ``adhesion_lag``: right when that class is named);
* ``rail``: the rail's fault curve 1-5 % less (or more) grippy, peak creep sometimes moved: a
  nuisance, whose right answer names no effect;
* ``two_effect``: one plant effect and one sensor effect at once;
* ``outside``: an effect outside every class (torque ripple, wheel radius, tachometer gain): right answer
  "none", and a sparse description (``which.description``) naming what the missing term depends on;
* ``out_of_library``: a member of ``family()``, effects that are no candidate and that a combination of
  candidates can mimic, each classed in advance (``outside``: the right answer names no effect;
  ``nuisance``: the rail's curve is what differs): the drive's constant-power torque limit
  (``power_limit``: the torque capped at P_max / omega_m once the motor runs 0.5-5 % above its
  equilibrium speed; the rail curve and the drivetrain losses each remove most of its gap), a rail
  curve stretched (or shrunk) in creep by 6-14 % (``rail_stretch``, inside the nuisance's range 0.85-1.18;
  classed ``nuisance``), a torque map of the drive (``torque_map``: the torque gain falling by
  ``droop`` 0.5-3 times the motor's relative speed rise above its equilibrium speed, acting from the
  start; ``outside``) and a stuck motor encoder (``sensor_stick``: its last reading repeated for 5-30
  ms from a time drawn in 0.2-0.65 s; ``outside``: no candidate holds a reading), the rail's curve changed
  in shape at low creep (``rail_shape``: stretched or squeezed by 15-35 % near zero creep, fading over
  0.3-1 km/h, peak and tail kept; classed ``nuisance``: no scaling of the whole curve makes it, and a
  static load transfer at a few centimetres' height used to stand for it) and a quantiser under noise
  (``quantiser_noise``: the motor encoder's lattice, q 0.04-0.2 rad/s, with noise q/60-q/30 added after
  it; classed ``library``: the right answer names ``sensor_quantisation``, whose detector took the
  quantum from the smallest steps and missed it before issue 51);
* ``nominal``: no effect at all (right answer: no gap, "none").

Each run is recorded to MCAP, diagnosed through ``hil.gap.read_real_log`` (which drops the truth
key), and only then compared with the truth.  Scores: top-1 (single effects: the named class is the
truth's class), set accuracy (``named_set`` equals the truth's classes), "none" accuracy (rail and
outside cases), false-confident rate (a named class absent from the truth: every name claims at least
``MIN_SHRINK`` of the gap), both-found rate of two-effect cases, median held-out shrink when right,
parameter error where the forms match.

Per grade (``calibration``), the fraction of right answers (issue 35): ``confident`` / ``tentative``
right when every effect named (for ``tentative`` the "most likely" one) is a true effect;
``not_separable`` when its list holds every true class (a pair listed holds both of its classes; the
rail curve for a nuisance; any list for a truth outside the library); ``nuisance`` when the rail's
curve differs; ``none`` when the truth is outside the library, nominal, or beyond what the log tells
apart (the oracle).  ``--doc DIR`` writes it to ``DIR/gap-calibration.json``, which ``hil gap`` prints
beside its answer.

Not drawn: ``torque_lag``.  The TCU commands a constant torque, so a first-order torque lag never
acts and no diagnosis can see it (the gap is zero); it stays in the library and among the candidates.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..effects import EFFECTS
from ..sweep.engine import map_in_order
from ..terminal import wrap, wrap_lines


def _draws(kind: str) -> dict:
    """effect -> its record's draw of ``kind`` (``hil.effects.Draw``), in the registry's order."""
    return {n: s.draw(kind) for n, s in EFFECTS.items() if s.draw(kind) is not None}


# every table below is read off the effects' records (``hil.effects``: ``EffectSpec.draws``) when a case
# is drawn, so an effect added with ``hil.effects.add_effect`` is drawn too
def library() -> dict:
    """The candidates' own forms: effect -> (the parameter the diagnosis must recover, sampler(rng) -> params)."""
    return {n: (d.recover, d.sample) for n, d in _draws("library_form").items()}


def held_out() -> dict:
    """Forms the candidate list does not use (their class: ``EFFECTS[name].effect_class``) -> sampler."""
    return {n: d.sample for n, d in _draws("held_out_form").items()}


def outside() -> dict:
    """Effects of no candidate's class -> sampler."""
    return {n: d.sample for n, d in _draws("outside").items()}


def rail_draw(g) -> dict:
    """The rail's fault curve 1-5 % off (the ``rail`` kind)."""
    return _draws("rail")["rail_curve"].sample(g)


def family() -> dict:
    """The out-of-library family: member -> (its class, decided before any diagnosis: "outside" (no
    effect is right) or "nuisance" (the rail's curve differs), the reality effect that makes it,
    sampler(rng) -> its parameters).  None is a candidate (``EFFECTS[effect].candidate`` is False); why
    each is drawn as it is: its record's comment."""
    return {d.member: (d.member_class, n, d.sample) for n, d in _draws("out_of_library").items()}


def paired_forms() -> tuple[tuple, tuple]:
    """(plant forms, sensor or bus forms) the two-effect cases draw one of each from, by ``Draw.pair_rank``."""
    paired = sorted((d.pair_rank, n) for kind in ("library_form", "held_out_form")
                    for n, d in _draws(kind).items() if d.pair_rank)
    return (tuple(n for _, n in paired if EFFECTS[n].level == "plant"),
            tuple(n for _, n in paired if EFFECTS[n].level != "plant"))


#: what the missing term of each out-of-library effect depends on: a sparse description of the gap
#: (``which.description``) is right when it names one of these (a tachometer gain scales the motor
#: speed read; a wheel radius error changes the creep a wheel speed makes; a torque ripple rides on the
#: torque), or, for a periodic effect, when its periodic term is at the truth's frequency
#: (``LINE_TOLERANCE``; a torque ripple under a command constant over the window: nothing in the log
#: says the sine scales with the torque)
OUTSIDE_VARIABLES = {"torque_ripple": {"torque"}, "wheel_radius": {"creep_speed", "motor_speed"},
                     "tachometer_gain": {"motor_speed"}, "power_limit": {"motor_speed", "torque"},
                     "torque_map": {"motor_speed", "torque"}, "sensor_stick": {"motor_speed"}}
LINE_TOLERANCE = 0.02
KINDS = ("held_out_form", "library_form", "rail", "two_effect", "outside", "out_of_library", "nominal")
#: the five first kinds in the proportions they always had; the out-of-library family and the nominal row beside
DEFAULT_MIX = {"held_out_form": 0.4, "library_form": 0.15, "rail": 0.15, "two_effect": 0.1, "outside": 0.2,
               "out_of_library": 0.15, "nominal": 0.05}
GRADES = ("confident", "tentative", "not_separable", "nuisance", "none")


def _sample(name: str, g) -> dict:
    for table in (library(), held_out()):
        if name in table:
            return table[name][1](g) if isinstance(table[name], tuple) else table[name](g)
    return outside()[name](g)


def truth_classes(effects: dict) -> list[str]:
    """The classes a right answer names: effects that are no candidate (outside every class, the rail,
    the out-of-library family) name none."""
    return sorted({EFFECTS[n].effect_class for n in effects if EFFECTS[n].candidate})


def member_of(kind: str, effects: dict) -> str | None:
    """The out-of-library family member a case was drawn as (None for the other kinds)."""
    if kind != "out_of_library":
        return None
    return next(m for m, (_, effect, _) in family().items() if effect in effects)


def register(sub) -> None:
    p = sub.add_parser("gap", help="blind check of hil gap on runs with one random hidden effect each")
    p.add_argument("scenario", nargs="?", default="scenarios/ffcc_a.toml")
    p.add_argument("--cases", type=int, default=24, help="number of real runs (default 24)")
    p.add_argument("--seed", type=int, default=None, help="seed of the case draws (default: drawn now, printed)")
    p.add_argument("--mix", default=None,
                   help="case mix KIND=F,... over " + ", ".join(KINDS) + " (default "
                   + ",".join(f"{k}={v}" for k, v in DEFAULT_MIX.items()) + ")")
    p.add_argument("--doc", metavar="DIR", default=None, help="write gap.md and gap.json into DIR (e.g. docs/benchmarks)")
    p.add_argument("--out", default=None, help="keep the MCAP logs here (default: a temporary directory)")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")
    p.add_argument("--markdown", action="store_true", help="print the report's markdown (gap.md) instead of the "
                   "short summary")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None, help="run the cases on this Dask cluster "
                   "(tcp://HOST:PORT; hil sweep's engine)")
    p.add_argument("--workers", type=int, default=None, help="run the cases on a local Dask cluster of this many "
                   "worker processes (default: serially in this process)")
    p.set_defaults(func=cmd_gap_bench)


def parse_mix(text: str | None) -> dict:
    from ..errors import ConfigError
    if not text:
        return dict(DEFAULT_MIX)
    mix = {k: 0.0 for k in KINDS}
    for item in text.split(","):
        k, _, v = item.partition("=")
        if k.strip() not in mix:
            raise ConfigError(f"--mix {text!r}: unknown kind {k.strip()!r} (known: {', '.join(KINDS)})")
        try:
            mix[k.strip()] = float(v)
        except ValueError:
            raise ConfigError(f"--mix {text!r}: {item!r} is not KIND=FRACTION") from None
    if not all(v >= 0 for v in mix.values()) or sum(mix.values()) <= 0:
        raise ConfigError(f"--mix {text!r}: fractions must be >= 0 with a positive sum")
    return mix


def draw_case(seed: int, i: int, mix: dict) -> tuple[str, dict, int]:
    """(kind, {effect: params}, run seed) of case i: a pure function of (seed, i, mix)."""
    g = np.random.default_rng([seed, i, 0x6A9])
    kinds = list(mix)
    w = np.array([mix[k] for k in kinds], float)
    kind = kinds[int(g.choice(len(kinds), p=w / w.sum()))]
    if kind == "held_out_form":
        forms = sorted(held_out())
        name = forms[int(g.integers(len(forms)))]
        effects = {name: _sample(name, g)}
    elif kind == "library_form":
        forms = sorted(library())
        name = forms[int(g.integers(len(forms)))]
        effects = {name: _sample(name, g)}
    elif kind == "rail":
        effects = {"rail_curve": rail_draw(g)}
    elif kind == "two_effect":
        plant_forms, sensor_forms = paired_forms()
        a = plant_forms[int(g.integers(len(plant_forms)))]
        b = sensor_forms[int(g.integers(len(sensor_forms)))]
        effects = {a: _sample(a, g), b: _sample(b, g)}
    elif kind == "outside":
        names = sorted(outside())
        name = names[int(g.integers(len(names)))]
        effects = {name: _sample(name, g)}
    elif kind == "out_of_library":
        members = family()
        _, effect, sampler = members[sorted(members)[int(g.integers(len(members)))]]
        effects = {effect: sampler(g)}
    else:                                  # nominal: no effect
        effects = {}
    return kind, effects, int(g.integers(1, 2 ** 31 - 1))


def truth_value(effect: str, truth: dict) -> float | None:
    """The parameter value the diagnosis must recover, from the log's truth record (library forms)."""
    if effect not in library():
        return None
    params = json.loads(truth["effects"])[effect]
    if effect == "can":   # the TCU sees whole periods: the realised mean delay is the recoverable figure
        return json.loads(truth["can_realised"])["mean_delay_ms"]
    return params[library()[effect][0]]


def run_case(scenario, kind: str, effects: dict, run_seed: int, out_dir: Path, i: int) -> dict:
    from ..gap import diagnose, read_real_log
    from ..log.read import read_log
    from ..exchange import run
    from ..effects import TRUTH_KEY, with_reality

    real = with_reality(scenario, effects)
    summary = run(real, "nlls", run_seed, bus="inprocess", out_dir=out_dir / f"case{i:03d}", progress=False,
                  log=lambda text: None)
    path = summary["mcap"]
    t0, c0 = time.perf_counter(), time.process_time()
    held = sorted(n for n in effects if n in held_out())             # the truth's own form is no candidate
    out, result = diagnose(read_real_log(path), scenario, identify=False, exclude=held)   # blind: no truth here
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    truth = read_log(path).metadata.get(TRUTH_KEY, {})                  # only now, for scoring (none: nominal)
    which = out["which"]
    truth_set = truth_classes(effects)
    limit = oracle(result, effects, truth_set) if which["gap_present"] and truth_set else None
    named_set = sorted(which["named_set"])
    rec = {"case": i, "kind": kind, "effects": effects, "truth_classes": truth_set, "named": which["named"],
           "named_set": named_set, "confidence": which["confidence"], "verdict": which["verdict"],
           "set_correct": named_set == truth_set,
           "false_confident": bool(set(named_set) - set(truth_set)),
           "shrink_percent": out["shrink"]["held_out_gap_shrink_percent"],
           "nominal_gap": which["nominal_held_out_gap"], "best": which["ranking"][0]["effect"],
           "best_form": which["ranking"][0]["form"], "diagnosis_s": wall, "diagnosis_cpu_s": cpu, "log": path,
           "description": (which.get("description") or {}).get("sentence"),
           "described_variables": (which.get("description") or {}).get("variables", []),
           "oracle": limit, "excluded": held, "ranked_candidates": [r["candidate"] for r in which["ranking"]],
           "failed_candidates": which["failed_candidates"], "gap_present": which["gap_present"],
           "member": member_of(kind, effects),
           "not_separable": ["+".join(a.get("effects") or [a["effect"]]) for a in which.get("not_separable") or []],
           "forward": {k: (which["forward"] or {}).get(k) for k in ("first", "second", "accepted", "rejected_because")}
           if which["forward"] else None,
           "forward_firsts": [f"{f['first']}+{f['second']}: {'accepted' if f['accepted'] else 'turned away'}"
                              for f in which.get("forward_firsts") or []],
           "veto_in_time": ((which["forward"] or {}).get("held_out_in_time") or {}).get("pair_wins")}
    rec["member_class"] = family()[rec["member"]][0] if rec["member"] else None
    if kind == "outside" or rec["member_class"] == "outside":
        right = set().union(*(OUTSIDE_VARIABLES[n] for n in effects))
        line_hz = (which.get("description") or {}).get("line_hz") if "periodic" in rec["described_variables"] \
            else None
        rec["described_line_hz"] = line_hz
        rec["description_right"] = bool(set(rec["described_variables"]) & right) or any(
            line_hz is not None and abs(line_hz / p["frequency_hz"] - 1) <= LINE_TOLERANCE
            for p in effects.values() if "frequency_hz" in p)
    if len(effects) == 1 and truth_set:
        rec["correct"] = which["named"] == truth_set[0]
    elif not truth_set:
        rec["correct"] = which["named"] == "none"
    else:
        rec["correct"] = rec["set_correct"]
    rec["grade_right"] = grade_right(rec, which)
    if kind == "rail":
        n = which["nuisances"]
        rec["rail_reported"] = bool(n) and "rail" in which["verdict"]
        if n:
            rec["rail_peak_mu_percent"] = n[0]["peak_mu_percent"]
            rec["rail_true_peak_mu_percent"] = (effects["rail_curve"]["peak_mu_scale"] - 1) * 100
    if kind == "library_form":
        effect = next(iter(effects))
        true_v = truth_value(effect, truth)
        rec["true_value"] = true_v
        if which["named"] == EFFECTS[effect].effect_class:
            # the library form's own fit (a quantiser is judged apart: ``which.quantiser``; a second form of a
            # class, adhesion_lag2, its own candidate's row whichever form of the class was named)
            row = which["quantiser"] if effect == "sensor_quantisation" and which.get("quantiser") else \
                next((r for r in which["ranking"] if r["candidate"] == effect), None)
            if row is not None:
                fitted = row["params"][library()[effect][0]]
                rec["fitted_value"] = fitted
                rec["param_err_percent"] = abs(fitted - true_v) / abs(true_v) * 100
    return rec


def grade_right(rec: dict, which: dict) -> bool:
    """Is the answer right for its grade (module docstring, issue 35 item 1)?  ``rec``: the case's record
    so far (truth classes, effects, oracle); ``which``: the diagnosis' answer."""
    truth, grade = set(rec["truth_classes"]), which["confidence"]
    rail = "rail_curve" in rec["effects"] or rec.get("member_class") == "nuisance"   # the rail's curve differs
    beyond = bool(rec.get("oracle")) and not rec["oracle"]["separable"]
    if grade == "confident":
        return bool(which["named_set"]) and set(which["named_set"]) <= truth
    if grade == "tentative":
        return which["ranking"][0]["effect"] in truth
    if grade == "not_separable":
        listed = {e for a in which.get("not_separable") or [] for e in a.get("effects") or [a["effect"]]}
        return truth <= listed and (not rail or "rail_curve" in listed)
    if grade == "nuisance":
        return rail
    return not truth or beyond      # none: outside, nominal or the rail with no gap, or beyond the log


def oracle(result, effects: dict, truth_set: list) -> dict | None:
    """The information limit of one case: the truth itself (its own equations and parameters, only
    the initial state fitted) scored as one more candidate by the diagnosis' own rules.  ``separable``:
    it removes a material share and beats, by the diagnosis' margin (``select.beats``), the rail
    nuisance and the best candidate of a class the truth does not have (of several effects: the best
    single candidate).  A case the truth itself cannot be
    told apart in is beyond what any candidate could be expected to name from this log.  None where a
    truth effect has no exact model here (quantisation, a tachometer gain, the CAN bus)."""
    from plant.reality import fill_defaults
    from ..gap.candidates import fit_nominal
    from ..gap.select import MIN_SCORE_GAIN, MIN_SHRINK, beats, entry

    plant = {n: p for n, p in effects.items() if EFFECTS[n].level == "plant"}
    sensor = {n: p for n, p in effects.items() if n not in plant}
    exact = {"sensor_delay": ("sensor_delay", "delay_ms"), "sensor_lowpass": ("lowpass_tau", "tau_ms"),
             "motor_delay": ("motor_delay", "delay_ms")}
    if set(sensor) - set(exact):
        return None
    periods = {exact[n][0]: p[exact[n][1]] * 1e-3 / result.data.period_s for n, p in sensor.items()}
    ctx = result.ctx.on_top_of_effects(
        fill_defaults({n: {**EFFECTS[n].params, **p} for n, p in plant.items()}, result.ctx.cfg), **periods)
    fit = fit_nominal(ctx)
    fit.name = "truth"
    row = entry(result.ctx, fit, result.base)
    # the alternatives: another class's best for one effect; for several, any single candidate too (a
    # pair is told apart only when it beats the best single effect: the second one shows)
    others = [r for r in result.ranking if len(truth_set) > 1 or r.effect not in truth_set]
    material = row.held_out_shrink >= MIN_SHRINK and row.score_gain > MIN_SCORE_GAIN
    over_rail = result.rail is None or beats(row, result.rail)
    over_others = all(beats(row, r) for r in others[:1])
    return {"shrink_percent": row.held_out_shrink * 100, "held_out_gap": row.held_out_gap,
            "score_gain": row.score_gain, "material": material, "beats_rail": over_rail,
            "beats_other_classes": over_others, "separable": bool(material and over_rail and over_others)}


def gap_case(job) -> dict:
    """Case ``i``: draw it, make the real run, diagnose it blind, score it.  Plain data in and out, so
    it runs on a Dask worker as well as here; the log goes to ``out/case<i>`` when ``out`` is given (on
    the machine that runs the case), else to a temporary directory removed after the case."""
    scenario, seed, i, mix, out = job
    kind, effects, run_seed = draw_case(seed, i, mix)
    if out:
        return run_case(scenario, kind, effects, run_seed, Path(out), i)
    with tempfile.TemporaryDirectory(prefix="hil-gap-bench-") as tmp:
        return run_case(scenario, kind, effects, run_seed, Path(tmp), i)


def _rate(rs, key="correct"):
    return sum(bool(r[key]) for r in rs) / len(rs) if rs else None


def summarise(records: list[dict]) -> dict:
    single = [r for r in records if r["kind"] in ("held_out_form", "library_form")]
    held = [r for r in records if r["kind"] == "held_out_form"]
    nones = [r for r in records if r["kind"] in ("rail", "outside")]
    two = [r for r in records if r["kind"] == "two_effect"]
    shrinks = [r["shrink_percent"] for r in records if r["correct"] and r["truth_classes"]]
    perr = [r["param_err_percent"] for r in records if "param_err_percent" in r]
    per_form = {}
    for r in records:
        key = "+".join(sorted(r["effects"])) or "nominal"
        d = per_form.setdefault(key, {"cases": 0, "correct": 0})
        d["cases"] += 1
        d["correct"] += int(r["correct"])
    labels = sorted({c for r in records for c in r["truth_classes"]} | {r["named"] for r in records} | {"none"})
    confusion = {}
    for r in records:
        row = "+".join(r["truth_classes"]) or "none"
        confusion.setdefault(row, {n: 0 for n in labels})[r["named"]] += 1
    sep = lambda rs: [r for r in rs if (r.get("oracle") or {}).get("separable")]  # noqa: E731
    beyond = lambda rs: [r for r in rs if r.get("oracle") and not r["oracle"]["separable"]]  # noqa: E731
    ool = [r for r in records if r["kind"] == "out_of_library"]
    outside_like = [r for r in records if r["kind"] in ("rail", "outside", "out_of_library")]
    confident = [r for r in records if r["confidence"] == "confident"]
    confident_wrong = sum(not r["grade_right"] for r in confident)
    # `not_separable` answers whose truth is in the library: right when the list holds every true class
    listed = [r for r in records if r["confidence"] == "not_separable" and r["truth_classes"]]
    # the effects outside the library and the family's outside and nuisance members: no effect is right
    unnamed = [r for r in records if r["kind"] == "outside" or r.get("member_class") in ("outside", "nuisance")]
    family_library = [r for r in ool if r.get("member_class") == "library"]
    return {
        "cases": len(records), "by_kind": {k: sum(r["kind"] == k for r in records) for k in KINDS},
        "calibration": calibration(records),
        "confident_wrong": confident_wrong, "confident_cases": len(confident),
        "confident_wrong_upper95": upper95(confident_wrong, len(confident)),
        "confident_wrong_outside_and_nuisance": sum(r["confidence"] == "confident" and not r["grade_right"]
                                                    for r in outside_like),
        "outside_and_nuisance_cases": len(outside_like),
        "not_separable_library_truth": len(listed),
        "not_separable_lists_truth": _rate(listed, "grade_right"),
        "none_accuracy_out_of_library": _rate(ool), "grade_right_out_of_library": _rate(ool, "grade_right"),
        "outside_cases": len(unnamed),
        "outside_none_not_separable_nuisance": _rate([dict(r, unnamed=r["confidence"] in (
            "none", "not_separable", "nuisance")) for r in unnamed], "unnamed"),
        "family_library_cases": len(family_library), "family_library_named": _rate(family_library),
        "nominal_no_gap": _rate([dict(r, no_gap=not r["gap_present"]) for r in records if r["kind"] == "nominal"],
                                "no_gap"),
        "oracle_cases": sum(bool(r.get("oracle")) for r in records),
        "held_out_separable": len(sep(held)), "held_out_beyond_the_log": len(beyond(held)),
        "top1_accuracy_held_out_separable": _rate(sep(held)),
        "two_effect_separable": len(sep(two)), "two_effect_beyond_the_log": len(beyond(two)),
        "two_effect_both_found_separable": _rate(sep(two), "set_correct"),
        "wrong_beyond_the_log": sum(not r["correct"] for r in beyond(records)),
        "wrong_separable": sum(not r["correct"] for r in sep(records)),
        "top1_accuracy": _rate(single), "top1_accuracy_held_out_forms": _rate(held),
        "top1_accuracy_library_forms": _rate([r for r in records if r["kind"] == "library_form"]),
        "set_accuracy": _rate(records, "set_correct"),
        "none_accuracy": _rate(nones), "none_accuracy_rail": _rate([r for r in nones if r["kind"] == "rail"]),
        "none_accuracy_outside": _rate([r for r in nones if r["kind"] == "outside"]),
        "description_right_outside": _rate([r for r in nones if r["kind"] == "outside"], "description_right"),
        "outside_with_gap": sum(1 for r in nones if r["kind"] == "outside" and r.get("gap_present")),
        "description_right_outside_with_gap": _rate([r for r in nones if r["kind"] == "outside"
                                                     and r.get("gap_present")], "description_right"),
        # the out-of-library family's members classed outside (a nuisance member is described by the rail)
        "description_right_family": _rate([r for r in ool if r.get("member_class") == "outside"],
                                          "description_right"),
        "family_outside_cases": sum(r.get("member_class") == "outside" for r in ool),
        "rail_reported": _rate([r for r in records if r["kind"] == "rail"], "rail_reported"),
        "false_confident_rate": _rate(records, "false_confident"),
        "two_effect_both_found": _rate(two, "set_correct"),
        "median_shrink_percent": float(np.median(shrinks)) if shrinks else None,
        "median_param_err_percent": float(np.median(perr)) if perr else None,
        "param_within_20_percent": sum(p <= 20 for p in perr) / len(perr) if perr else None,
        "per_form": per_form, "confusion": confusion,
        "failed_fits": sum(len(r.get("failed_candidates", [])) for r in records),
        "median_diagnosis_s": float(np.median([r["diagnosis_s"] for r in records])) if records else None,
        # the CPU seconds of this process (a loaded machine stretches the wall seconds, not these)
        "median_diagnosis_cpu_s": float(np.median([r["diagnosis_cpu_s"] for r in records])) if records else None,
    }


def calibration(records: list[dict]) -> dict:
    """Per grade: cases, right answers (``grade_right``), their fraction and its 95 % interval (Clopper-Pearson)."""
    out = {}
    for g in GRADES:
        rs = [r for r in records if r["confidence"] == g]
        k = sum(bool(r["grade_right"]) for r in rs)
        out[g] = {"cases": len(rs), "right": k, "fraction": k / len(rs) if rs else None,
                  "interval95": [1 - upper95(len(rs) - k, len(rs)), upper95(k, len(rs))] if rs else None}
    return out


def upper95(k: int, n: int) -> float | None:
    """The 95 % Clopper-Pearson upper bound of a rate seen k times in n (two-sided, 2.5 % each side)."""
    from scipy.stats import beta
    if n == 0:
        return None
    return 1.0 if k >= n else float(beta.ppf(0.975, k + 1, n - k))


def markdown(result: dict) -> str:
    from ..trace import fmt as f
    pct = lambda v: "-" if v is None else f"{v * 100:.0f} %"  # noqa: E731
    lines = ["# `hil bench gap`: the blind check of `hil gap`", "",
             f"Written by `hil bench gap {result['scenario']} --cases {result['cases']} --seed {result['seed']}"
             f"{' --mix ' + result['mix_arg'] if result.get('mix_arg') else ''}"
             f"{' --doc ' + str(result['doc_arg']) if result.get('doc_arg') else ''}` "
             f"(seed drawn at run time: {result['seed_drawn']}); wall {result['wall_s']:.0f} s, "
             f"median diagnosis {f(result['median_diagnosis_s'], '.1f')} s "
             f"({f(result.get('median_diagnosis_cpu_s'), '.1f')} s of CPU).", "",
             "Cases by kind: " + ", ".join(f"{k} {v}" for k, v in result["by_kind"].items()), "",
             "| figure | measured | target (issues 18 and 35) |", "|---|---|---|",
             f"| top-1, single effects in a held-out form | {pct(result['top1_accuracy_held_out_forms'])} | >= 80 % of "
             "those told apart, never a wrong class |",
             f"| top-1, single effects in the candidates' form | {pct(result['top1_accuracy_library_forms'])} | - |",
             f"| set accuracy (all cases) | {pct(result['set_accuracy'])} | - |",
             f"| false-confident rate (all cases) | {pct(result['false_confident_rate'])} | <= 2 % |",
             f"| 'none' on rail curves 1-5 % off | {pct(result['none_accuracy_rail'])} | - |",
             f"| rail curve reported as the rail | {pct(result['rail_reported'])} | - |",
             f"| 'none' on out-of-library effects | {pct(result['none_accuracy_outside'])} | >= 80 % |",
             f"| sparse description names the right variable (outside: ripple, wheel radius, tachometer) | "
             f"{pct(result.get('description_right_outside'))} | >= 50 % |",
             f"| sparse description names the right variable (out-of-library family, members classed outside: "
             f"{result.get('family_outside_cases', 0)}) | {pct(result.get('description_right_family'))} | >= 50 % |",
             f"| ... where the log shows a gap to describe ({result.get('outside_with_gap')} of "
             f"{result['by_kind'].get('outside', 0)}) | {pct(result.get('description_right_outside_with_gap'))} | "
             "(the limit) |",
             f"| two-effect cases, both found | {pct(result['two_effect_both_found'])} | >= 70 % |",
             f"| confident answers wrong | {result.get('confident_wrong')} of {result.get('confident_cases')} "
             f"(95 % upper bound {pct(result.get('confident_wrong_upper95'))}) | <= 2 of >= 100 |",
             f"| confident wrong among rail, outside and out-of-library cases | "
             f"{result.get('confident_wrong_outside_and_nuisance')} of {result.get('outside_and_nuisance_cases')} | "
             "0 of >= 60 |",
             f"| 'not_separable' lists every true class, truth in the library "
             f"({result.get('not_separable_library_truth', 0)} answers) | "
             f"{pct(result.get('not_separable_lists_truth'))} | >= 90 % |",
             f"| out-of-library family: right answer / right for its grade | "
             f"{pct(result.get('none_accuracy_out_of_library'))} / {pct(result.get('grade_right_out_of_library'))} | "
             ">= 90 % |",
             f"| outside effects and the family's outside and nuisance members "
             f"({result.get('outside_cases', 0)}): answered none, not_separable or nuisance | "
             f"{pct(result.get('outside_none_not_separable_nuisance'))} | 100 % |",
             f"| the family's library members (a quantiser under noise; {result.get('family_library_cases', 0)}): "
             f"the class named | {pct(result.get('family_library_named'))} | - |",
             f"| nominal row: no gap | {pct(result.get('nominal_no_gap'))} | 100 % |",
             f"| ... held-out forms where the truth itself is told apart ({result['held_out_separable']} of "
             f"{result['by_kind']['held_out_form']}; {result['held_out_beyond_the_log']} beyond the log) | "
             f"{pct(result['top1_accuracy_held_out_separable'])} | (the limit) |",
             f"| ... two-effect cases where the truth itself is told apart ({result['two_effect_separable']} of "
             f"{result['by_kind']['two_effect']}; {result['two_effect_beyond_the_log']} beyond the log) | "
             f"{pct(result['two_effect_both_found_separable'])} | (the limit) |",
             f"| median held-out shrink when right | {f(result['median_shrink_percent'], '.1f')} % | >= 80 % |",
             f"| median parameter error (matching forms) | {f(result['median_param_err_percent'], '.1f')} % | - |",
             "", "**The limit.** For each case whose truth has an exact model here (plant effects, the sensor "
             "delay forms) the bench scores the truth itself as one more candidate, its own equations and "
             "parameters with only the initial state fitted, by the diagnosis' own rules. Where even the truth "
             "does not remove 80 % of the held-out gap or does not beat the rail nuisance and the best "
             "candidate of another class by the margin, no candidate can be expected to be named from that log: "
             f"{result['wrong_beyond_the_log']} of the wrong answers are such cases, {result['wrong_separable']} "
             "are not (column 'truth told apart' below).",
             "", "## Each grade, calibrated", "", "| grade | cases | right | fraction (95 % interval) |",
             "|---|---|---|---|"]
    for g, c in (result.get("calibration") or {}).items():
        iv = c["interval95"]
        lines.append(f"| {g} | {c['cases']} | {c['right']} | {pct(c['fraction'])}"
                     + (f" ({iv[0] * 100:.0f}-{iv[1] * 100:.0f} %)" if iv else "") + " |")
    lines += ["", "## Per effect (or pair)", "", "| truth | cases | right |", "|---|---|---|"]
    for k, v in sorted(result["per_form"].items()):
        lines.append(f"| {k} | {v['cases']} | {v['correct']} |")
    lines += ["", "## Every case", "", "| # | kind | truth | named | confidence | shrink | truth told apart "
              "(its shrink) | verdict |", "|---|---|---|---|---|---|---|---|"]
    for r in result["records"]:
        truth = "; ".join(f"{n}(" + ", ".join(f"{k}={v:.4g}" for k, v in p.items() if v is not None) + ")"
                          for n, p in r["effects"].items())
        truth = (f"{r['member']}: " if r.get("member") else "") + (truth or "nominal")
        lines.append(f"| {r['case']} | {r['kind']} | {truth} | {r['named']} | {r['confidence']} | "
                     f"{r['shrink_percent']:.0f} % | {_oracle_cell(r.get('oracle'))} | "
                     f"{r['verdict'][:160].replace('|', '/')} |")
    lines.append("")
    return "\n".join(lines)


def _oracle_cell(o) -> str:
    if not o:
        return "-"
    why = [] if o["separable"] else [w for w, ok in (("< 80 %", o["material"]), ("not over the rail", o["beats_rail"]),
                                                       ("not over another class", o["beats_other_classes"])) if not ok]
    return ("yes" if o["separable"] else "no: " + ", ".join(why)) + f" ({o['shrink_percent']:.0f} %)"


def cmd_gap_bench(args) -> int:
    from ..errors import ConfigError
    from ..config import load_scenario
    from ..trace import clean

    if args.cases < 1:
        raise ConfigError(f"--cases {args.cases}: must be >= 1")
    mix = parse_mix(args.mix)
    seed_drawn = args.seed is None
    seed = int.from_bytes(os.urandom(4), "little") % (1 << 31) if seed_drawn else args.seed
    print(f"hil bench gap: seed {seed}" + (" (drawn now)" if seed_drawn else ""), file=sys.stderr, flush=True)
    scenario = load_scenario(args.scenario)
    records = []
    wall0 = time.perf_counter()
    jobs = [(scenario, seed, i, mix, args.out) for i in range(args.cases)]
    # one case per call, serially here or on Dask (--scheduler / --workers): the same records either way
    for rec in map_in_order(gap_case, jobs, args.scheduler, args.workers,
                            lambda done, i: print(f"hil bench gap: {done}/{args.cases} cases done (case {i})",
                                                  file=sys.stderr, flush=True)):
        records.append(rec)
        extra = f" param err {rec['param_err_percent']:.1f} %" if "param_err_percent" in rec else ""
        print(wrap(f"hil bench gap: case {rec['case'] + 1}/{args.cases}: {rec['kind']} "
                   f"{rec.get('member') or '+'.join(rec['effects']) or 'nominal'} -> "
                   f"{'+'.join(rec['named_set']) or 'none'} [{rec['confidence']}"
                   f"{': ' + ' or '.join(rec['not_separable']) if rec.get('not_separable') else ''}] "
                   f"({'ok' if rec['correct'] else 'WRONG'}{', FALSE-CONFIDENT' if rec['false_confident'] else ''}; "
                   f"grade {'right' if rec['grade_right'] else 'wrong'}), "
                   f"shrink {rec['shrink_percent']:.0f} %{extra}; truth told apart: {_oracle_cell(rec.get('oracle'))}"
                   + (f"; {len(rec['failed_candidates'])} candidate fits failed: "
                      + ", ".join(f"{f['name']} ({f['step']})" for f in rec["failed_candidates"])
                      if rec["failed_candidates"] else ""), indent="    "),
              file=sys.stderr, flush=True)
    result = summarise(records)
    result.update({"seed": seed, "seed_drawn": seed_drawn, "mix": mix, "mix_arg": args.mix, "doc_arg": args.doc,
                   "scenario": scenario.path, "wall_s": time.perf_counter() - wall0,
                   "records": [{k: v for k, v in r.items() if k != "log" or args.out} for r in records]})
    result = clean(result)
    if args.doc:
        from ..gap.calibration import CALIBRATION_FILE
        d = Path(args.doc)
        d.mkdir(parents=True, exist_ok=True)
        (d / "gap.json").write_text(json.dumps(result, indent=1) + "\n")
        (d / "gap.md").write_text(markdown(result))
        (d / CALIBRATION_FILE).write_text(json.dumps(
            {"seed": result["seed"], "cases": result["cases"], "mix": result["mix"], "scenario": result["scenario"],
             "grades": result["calibration"]}, indent=1) + "\n")
        print(f"hil bench gap: wrote {d / 'gap.md'}, {d / 'gap.json'} and {d / CALIBRATION_FILE}", file=sys.stderr)
    if args.json:
        print(json.dumps(result))
    elif args.markdown:
        print(markdown(result), end="")
    else:
        print(wrap_lines(summary_text(result)))
    return 0


def summary_text(result: dict) -> str:
    """The figures a reader decides on, one paragraph each (``wrap_lines`` fits them to a terminal)."""
    from ..trace import fmt as f

    lines = []
    lines.append(f"gap bench: {result['cases']} cases (seed {result['seed']}): " +
                 ", ".join(f"{k} {v}" for k, v in result["by_kind"].items()))
    lines.append(f"  top-1 held-out forms {f(result['top1_accuracy_held_out_forms'], '.3f')}, library forms "
                 f"{f(result['top1_accuracy_library_forms'], '.3f')}; set accuracy {f(result['set_accuracy'], '.3f')}; "
                 f"'none' accuracy {f(result['none_accuracy'], '.3f')} (rail {f(result['none_accuracy_rail'], '.3f')}, "
                 f"outside {f(result['none_accuracy_outside'], '.3f')}); outside described by the right "
                 f"variable {f(result.get('description_right_outside'), '.3f')} "
                 f"({f(result.get('description_right_outside_with_gap'), '.3f')} of the "
                 f"{result.get('outside_with_gap')} with a gap), the out-of-library family's outside members "
                 f"{f(result.get('description_right_family'), '.3f')} of {result.get('family_outside_cases', 0)}")
    lines.append(f"  false-confident rate {f(result['false_confident_rate'], '.3f')}; two effects both found "
                 f"{f(result['two_effect_both_found'], '.3f')}; median shrink when right "
                 f"{f(result['median_shrink_percent'], '.1f')} %; median parameter error "
                 f"{f(result['median_param_err_percent'], '.2f')} %; median diagnosis "
                 f"{f(result.get('median_diagnosis_s'), '.1f')} s ({f(result.get('median_diagnosis_cpu_s'), '.1f')} s "
                 f"of CPU)")
    cal = result.get("calibration")
    if cal:
        lines.append("  right per grade: " + ", ".join(f"{g} {c['right']} of {c['cases']}" for g, c in cal.items())
                     + f"; confident wrong {result['confident_wrong']} of {result['confident_cases']} (95 % upper "
                     f"bound {f(result['confident_wrong_upper95'], '.3f')}); out-of-library right "
                     f"{f(result['none_accuracy_out_of_library'], '.3f')}; outside and nuisance members answered "
                     f"none, not_separable or nuisance {f(result.get('outside_none_not_separable_nuisance'), '.3f')} "
                     f"of {result.get('outside_cases', 0)}; a quantiser under noise named "
                     f"{f(result.get('family_library_named'), '.3f')} of {result.get('family_library_cases', 0)}; "
                     f"nominal no gap "
                     f"{f(result['nominal_no_gap'], '.3f')}; 'not_separable' lists every true class "
                     f"{f(result.get('not_separable_lists_truth'), '.3f')} of the "
                     f"{result.get('not_separable_library_truth', 0)} with the truth in the library")
    lines.append(f"  the limit (the truth scored as a candidate, {result['oracle_cases']} cases): held-out forms told "
                 f"apart {result['held_out_separable']} (top-1 there {f(result['top1_accuracy_held_out_separable'], '.3f')}), "
                 f"beyond the log {result['held_out_beyond_the_log']}; two-effect told apart "
                 f"{result['two_effect_separable']} (both found there {f(result['two_effect_both_found_separable'], '.3f')}), "
                 f"beyond the log {result['two_effect_beyond_the_log']}; wrong answers beyond the log "
                 f"{result['wrong_beyond_the_log']}, told apart {result['wrong_separable']}")
    return "\n".join(lines)
