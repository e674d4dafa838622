"""The gap report: a markdown page with PNG plots (matplotlib, headless), and the text summary."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..trace import fmt as _f
from .candidates import SIGNALS, UNITS

STAGES = ("normal", "early", "serious")


def text_summary(out: dict) -> str:
    w, which, sh = out["where"], out["which"], out["shrink"]
    lines = [f"gap diagnosis of {out['real_log']} against model {out['model']}",
             f"  analysed {out['analysis_periods']} of {out['periods']} periods "
             f"({out['held_out_periods']} held out, blocks of {out['block_periods']})",
             f"  WHERE: {w['summary']}",
             "    per signal (RMSE / noise floor): " + ", ".join(
                 f"{s} {w['per_signal'][s]['rmse_in_noise_units']:.2f}" for s in w["per_signal"]),
             "    per stage: " + "; ".join(
                 f"{st} ({w['per_stage'][st]['periods']}): " + " ".join(
                     f"{s}={_f(w['per_stage'][st][s], '.2f')}" for s in SIGNALS) for st in STAGES),
             f"    T_det measured {_f(w['t_det_measured_s'])} s vs model {_f(w['t_det_model_s'])} s",
             "    whiteness (Ljung-Box p): " + ", ".join(
                 f"{s} {_f(w['tests'][s]['ljung_box_p'], '.2g')}" for s in SIGNALS)
             + ("; input constant: no input cross-correlation test" if w["input_constant"] else ""),
             f"  WHICH: {which['verdict']}"]
    cal = which.get("calibration")
    if cal:
        lines.append(f"    [{cal['sentence']} (hil bench gap, seed {cal['seed']}: {cal['path']})]")
    for r in which["ranking"]:
        bounds = [k for k, v in (r.get("at_bound") or {}).items() if v]
        lines.append(f"    {r['effect']:20s} {r.get('form', ''):18s} score gain {r['score_gain']:12.1f}  held-out gap "
                     f"shrink {r['held_out_shrink'] * 100:7.1f} %  " + ", ".join(
                         f"{k}={v:.4g}" + (f" [{_f((r.get('param_ci') or {}).get(k, [None])[0], '.3g')}, "
                                           f"{_f((r.get('param_ci') or {}).get(k, [None, None])[1], '.3g')}]"
                                           if (r.get("param_ci") or {}).get(k) else "")
                         for k, v in r["params"].items()) + (f"  AT BOUND: {', '.join(bounds)}" if bounds else ""))
    if which.get("not_separable"):
        lines.append("    NOT SEPARABLE: " + "; ".join(
            f"{a['explanation']} removes {a['held_out_shrink'] * 100:.1f} %, leaves {a['held_out_gap']:.2f} noise units"
            for a in which["not_separable"]))
        for sb in which.get("separate_by_pairs") or []:
            lines.append(f"    separate by: {sb['between'][0]} vs {sb['between'][1]} differ most on {sb['signal']} in "
                         f"the {sb['stage']} stage ({sb['difference_noise_units']:.2f} noise units over "
                         f"{sb['periods']} periods)")
    tried = which.get("forward_firsts") or []
    if tried:
        lines.append("    PAIRS TRIED (forward selection, each first's best second): " + "; ".join(
            f"{f['second']} on {f['first']} removes {f['pair_held_out_shrink'] * 100:.1f} %: "
            + ("accepted" if f["accepted"] else "turned away (" + "; ".join(f["rejected_because"]) + ")")
            for f in tried))
    failed = which.get("failed_candidates") or []
    if failed:
        lines.append(f"    FAILED FITS ({len(failed)}; a candidate is not judged where its fit failed): " + "; ".join(
            f"{f['name']} ({f['form'] or f['effect']}, {f['step']}): {f['error']}" for f in failed))
    if which.get("description"):
        lines.append(f"    DESCRIBED (sparse regression of what the nominal model leaves): "
                     f"{which['description']['sentence']}")
    for u in which.get("unobservable", []):
        lines.append(f"    not observable in this log: {u['effect']} ({u['why']}); shows with {u['excitation']}")
    for n in which.get("nuisances", []):
        lines.append(f"    nuisance {n['name']}: peak mu {n['peak_mu_percent']:+.2f} %, peak creep "
                     f"{n['peak_creep_percent']:+.2f} %, held-out gap shrink {n['held_out_shrink'] * 100:.1f} %")
    lines.append(f"  HOW FAR ({sh['said']}): held-out gap "
                 f"shrink {sh['held_out_gap_shrink_percent']:.1f} %")
    for s, v in sh["per_signal"].items():
        lines.append(f"    {s:7s} RMSE {_f(v['rmse_before'], '.4g')} -> {_f(v['rmse_after'], '.4g')} {v['unit']}  (gap "
                     f"{_f(v['gap_before'])} -> {_f(v['gap_after'])}, noise floor {v['noise_floor']:.3g})")
    ident = out.get("identification")
    if ident:
        lines.append(f"  IDENTIFICATION ({ident['strategy']}):")
        for key in ("real", "nominal_replay", "augmented_replay"):
            if key in ident:
                r = ident[key]
                rng = r.get("rt_percent_range")
                rt_rng = f" [{_f(rng[0], '.0f')}-{_f(rng[1], '.0f')}]" if rng else ""
                lines.append(f"    {r['source']:32s} RT {_f(r.get('rt_percent'), '.1f')} %{rt_rng}  peak mu "
                             f"{_f(r.get('peak_mu'), '.4f')} (err {_f(r.get('peak_mu_err_percent'), '.2f')} %)  "
                             f"peak creep {_f(r.get('peak_creep_kmh'), '.3f')} km/h "
                             f"(err {_f(r.get('peak_creep_err_percent'), '.2f')} %)")
        lines.append(f"    (replays: median over {len(ident['nominal_replay']['seeds'])} sensor-noise draws; "
                     f"nominal replay peak mu range {_f((ident['nominal_replay'].get('peak_mu_range') or [None])[0], '.4f')}"
                     f"-{_f((ident['nominal_replay'].get('peak_mu_range') or [None, None])[1], '.4f')})")
        for k, v in ident["curve_shift"].items():
            lines.append(f"    {k}: {v}" if isinstance(v, bool) else f"    {k}: {_f(v, '+.2f')} %")
    return "\n".join(lines)


def write_report(out: dict, result, directory) -> Path:
    """report.md, PNG plots and gap.json of ``out`` (the answer) into ``directory``; the plots read the
    signals from ``result`` (a ``diagnose.DiagnosisResult``)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from identifier.curve import mu_model

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    a = {"meas": result.ctx.meas, "nominal": result.nominal, "best": result.best.pred, "best_name": result.best.name,
         "sigma": result.ctx.sigma_nom}
    t = result.data.t_s
    w = result.ctx.window
    pngs = []

    # 1. signals: measured, nominal, best candidate
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for ax, s in zip(axes, SIGNALS):
        ax.plot(t, a["meas"][s], ".", ms=1.5, color="0.5", label="measured")
        ax.plot(t, a["nominal"][s], "-", lw=1, color="tab:red", label="nominal model")
        ax.plot(t, a["best"][s], "--", lw=1, color="tab:blue", label=f"nominal + {a['best_name']}")
        ax.set_ylabel(f"{s} [{UNITS[s]}]")
        ax.axvspan(t[w][-1], t[-1], color="0.9", lw=0)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("t [s] (grey: outside the analysis window)")
    fig.tight_layout()
    fig.savefig(d / "signals.png", dpi=110)
    plt.close(fig)
    pngs.append("signals.png")

    # 2. residuals over time in noise units
    fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for ax, s in zip(axes, SIGNALS):
        ax.plot(t[w], ((a["meas"][s] - a["nominal"][s]) / a["sigma"][s])[w], lw=0.7, color="tab:red", label="nominal")
        ax.plot(t[w], ((a["meas"][s] - a["best"][s]) / a["sigma"][s])[w], lw=0.7, color="tab:blue",
                label=f"+ {a['best_name']}")
        ax.set_ylabel(f"{s} residual / noise")
        ax.set_yscale("symlog", linthresh=3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(d / "residuals.png", dpi=110)
    plt.close(fig)
    pngs.append("residuals.png")

    # 3. where: per creep band and per frequency band
    where = out["where"]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    labels = [f"{b['creep_kmh'][0]}-{b['creep_kmh'][1] or 'inf'}" for b in where["per_creep_band"]]
    x = np.arange(len(labels))
    for i, s in enumerate(SIGNALS):
        ax1.bar(x + (i - 1) * 0.27, [b[s] or 0 for b in where["per_creep_band"]], 0.27, label=s)
    ax1.set_xticks(x, labels)
    ax1.set_yscale("log")
    ax1.axhline(1, color="k", lw=0.8)
    ax1.set_xlabel("measured creep band [km/h]")
    ax1.set_ylabel("residual RMS / noise floor")
    ax1.legend(fontsize=8)
    labels = [f"{b['hz'][0]:g}-{b['hz'][1] or 'Nyq'}" for b in where["per_frequency_band"]]
    x = np.arange(len(labels))
    for i, s in enumerate(SIGNALS):
        ax2.bar(x + (i - 1) * 0.27, [b[s]["ratio"] or 0 for b in where["per_frequency_band"]], 0.27, label=s)
    ax2.set_xticks(x, labels)
    ax2.set_yscale("log")
    ax2.axhline(1, color="k", lw=0.8)
    ax2.set_xlabel("frequency band [Hz]")
    ax2.set_ylabel("residual RMS / noise RMS in band")
    fig.tight_layout()
    fig.savefig(d / "where.png", dpi=110)
    plt.close(fig)
    pngs.append("where.png")

    # 4. which: ranking
    rk = out["which"]["ranking"]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.barh([f"{r['effect']} ({r['form']})" for r in rk][::-1], [r["held_out_shrink"] * 100 for r in rk][::-1],
            color=["tab:green" if r["effect"] == out["which"]["named"] else "0.6" for r in rk][::-1])
    ax.axvline(out["which"]["rule"]["min_shrink"] * 100, color="k", ls="--", lw=0.8)
    ax.set_xlabel("held-out gap shrink [%] (dashed: minimum to name an effect; it must also beat the runner-up "
                  "and the rail-curve nuisance by a margin)", fontsize=8)
    ax.set_xlim(-20, 105)
    fig.tight_layout()
    fig.savefig(d / "which.png", dpi=110)
    plt.close(fig)
    pngs.append("which.png")

    # 5. the sparse description: what its view regresses against what the description says
    desc = out["which"].get("description")
    if desc and desc.get("described"):
        from .sparse import fitted, view_targets
        data = result.data
        target = view_targets(data.motor_speed_rad_s, result.nominal["motor"], data.period_s,
                              result.ahead_motor)[desc["view"]]
        fit = fitted(desc, data.motor_speed_rad_s, data.train_speed_ms, result.creep_meas, data.torque_cmd_nm,
                     data.period_s)
        held = result.ctx.held
        fig, ax = plt.subplots(figsize=(10, 3.8))
        ax.plot(t[w], target[w], ".", ms=1.5, color="0.6", label="what the nominal model leaves")
        ax.plot(t[held], target[held], ".", ms=1.5, color="tab:orange", label="... on the held-out blocks")
        ax.plot(t[w], fit[w], "-", lw=1.2, color="tab:blue",
                label=f"the description (held-out R² {desc['held_out_r2']:.2f})")
        ax.set_ylabel("motor-speed residual [rad/s]" if desc["view"] == "level"
                      else "acceleration the model lacks [rad/s²]")
        ax.set_xlabel("t [s]")
        ax.legend(loc="best", fontsize=8)
        fig.tight_layout()
        fig.savefig(d / "described.png", dpi=110)
        plt.close(fig)
        pngs.append("described.png")

    # 6. identified curves
    ident = out.get("identification")
    if ident:
        sc = result.scenario
        grid = np.linspace(0, 3 * sc.fault_curve.peak()[0], 300)
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(grid, sc.fault_curve.mu(grid), "k-", lw=1.5, label="model's fault curve")
        for key, style in (("real", "tab:red"), ("nominal_replay", "tab:orange"), ("augmented_replay", "tab:blue")):
            r = ident.get(key)
            if r and r.get("params"):
                ax.plot(grid, mu_model(grid, np.asarray(r["params"])), color=style, ls="--", label=r["source"])
        ax.set_ylim(-0.02, 1.6 * sc.fault_curve.peak()[1])   # an identified curve can dive near 0 creep
        ax.set_xlabel("creep speed [km/h]")
        ax.set_ylabel("mu")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(d / "curves.png", dpi=110)
        plt.close(fig)
        pngs.append("curves.png")

    md = ["# Sim-to-real gap report", "", f"Real log: `{out['real_log']}`  ", f"Model: `{out['model']}`", "",
          "```", text_summary(out), "```", ""]
    md += ["## Where", "", where["summary"], "", "![signals](signals.png)", "", "![residuals](residuals.png)", "",
           "![where](where.png)", "",
           "| stage | periods | " + " | ".join(SIGNALS) + " |", "|---|---|" + "---|" * len(SIGNALS)]
    for st in STAGES:
        v = where["per_stage"][st]
        md.append(f"| {st} | {v['periods']} | " + " | ".join(_f(v[s], ".2f") for s in SIGNALS) + " |")
    md += ["", "(residual RMS in noise-floor units; 1 = as good as the sensors)", "",
           "## Which effect", "", out["which"]["verdict"], "",
           *([f"What the nominal model leaves, described (sparse regression): "
              f"{out['which']['description']['sentence']}", "",
              *(["![described](described.png)", ""] if "described.png" in pngs else [])]
             if out["which"].get("description") else []),
           "![which](which.png)", "",
           "| effect | fitted parameters | score gain | held-out gap shrink |", "|---|---|---|---|"]
    for r in rk:
        md.append(f"| {r['effect']} | " + ", ".join(f"{k}={v:.4g}" for k, v in r["params"].items())
                  + f" | {r['score_gain']:.1f} | {r['held_out_shrink'] * 100:.1f} % |")
    if out["which"].get("failed_candidates"):
        md += ["", f"Candidate fits that failed ({len(out['which']['failed_candidates'])}; a candidate that failed "
               "alone is ranked with the nominal model's prediction):", "",
               "| candidate | form | step | error |", "|---|---|---|---|"]
        for f_ in out["which"]["failed_candidates"]:
            md.append(f"| {f_['name']} | {f_['form']} | {f_['step']} | {f_['error'].replace('|', '/')} |")
    md += ["", f"## How far it shrinks (held-out blocks): nominal + {out['shrink']['said']}", "",
           "| signal | RMSE before | RMSE after | gap before | gap after | noise floor |", "|---|---|---|---|---|---|"]
    for s, v in out["shrink"]["per_signal"].items():
        md.append(f"| {s} [{v['unit']}] | {_f(v['rmse_before'], '.4g')} | {_f(v['rmse_after'], '.4g')} | "
                  f"{_f(v['gap_before'])} | {_f(v['gap_after'])} | {v['noise_floor']:.3g} |")
    if ident:
        md += ["", "## Identification: real run vs model replays", "", "![curves](curves.png)", ""]
    md += ["", "Full figures: `gap.json`.", ""]
    (d / "report.md").write_text("\n".join(md))
    (d / "gap.json").write_text(json.dumps(out, indent=1))
    return d / "report.md"
