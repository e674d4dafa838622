"""What a person looks at after a sweep: a markdown summary and PNG plots of the main figures per axis.

``summary_markdown(df, axes, title)``: per axis, per value of it, the number of points, failed points,
and the median and spread (the 25th-75th percentile range) of each figure of ``FIGURES``; booleans
(identified, correct) as the fraction of the points that ran.  RT is over the identified points only
(a run that did not identify has no RT).  ``write_plots(df, axes, out_dir)``: one PNG per axis, a
panel per figure, every point as a dot and the median per axis value as a line.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .table import INPUT_PREFIX

#: the figures summarised and plotted: column -> (label, kind)
FIGURES = {
    "rt_percent": ("RT % (identified points)", "number"),
    "peak_mu_err_percent": ("peak mu error %", "number"),
    "peak_creep_err_percent": ("peak creep error %", "number"),
    "identified": ("identified (fraction)", "fraction"),
    "correct": ("correct (fraction)", "fraction"),
    "adhesion_utilisation_low": ("adhesion utilisation where it matters", "number"),
    "macro_slip_s": ("macro-slip s", "number"),
    "bus_load_percent": ("bus load %", "number"),
    "point_wall_s": ("wall time per point s", "number"),
}


def _label(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v) if not isinstance(v, (list, dict)) else json.dumps(v)


def _values(sub, column):
    import numpy as np

    x = sub[column].dropna()
    return np.asarray(x.astype(float), float) if len(x) else np.asarray([], float)


def _cell(sub, column, kind) -> str:
    import numpy as np

    ran = sub[sub["error"].isna()] if "error" in sub else sub
    x = _values(ran, column)
    if kind == "fraction":
        return "n/a" if not len(x) else f"{np.mean(x) * 100:.0f} %"
    if not len(x):
        return "n/a"
    q25, q50, q75 = np.percentile(x, [25, 50, 75])
    return f"{q50:.4g} [{q25:.4g}, {q75:.4g}]"


def axis_groups(df, name):
    """(label, rows) per value of axis ``name`` in the order the values first appear."""
    col = INPUT_PREFIX + name
    order = list(dict.fromkeys(df[col].tolist()))
    return [(_label(v), df[df[col] == v]) for v in order]


def summary_markdown(df, axes: dict, title: str, notes: list[str] = ()) -> str:
    lines = [f"# {title}", ""]
    lines += list(notes)
    ok = int(df["error"].isna().sum()) if len(df) else 0
    lines += ["", f"{len(df)} points, {ok} ran, {len(df) - ok} failed.  Each cell: median [25th, 75th percentile] "
              "over the points with that axis value (RT over the identified ones); identified and correct as the "
              "fraction of the points that ran (correct: confirmed with peak mu within 3 % and peak creep within "
              "10 % of the truth).", ""]
    for name in axes:
        if INPUT_PREFIX + name not in df:
            continue
        lines += [f"## {name}", "",
                  "| " + name + " | points | failed | " + " | ".join(label for label, _ in FIGURES.values()) + " |",
                  "|---|---|---|" + "---|" * len(FIGURES)]
        for label, sub in axis_groups(df, name):
            failed = int(sub["error"].notna().sum())
            lines.append(f"| {label} | {len(sub)} | {failed} | "
                         + " | ".join(_cell(sub, col, kind) for col, (_, kind) in FIGURES.items()) + " |")
        lines.append("")
    errors = df[df["error"].notna()] if len(df) else df
    if len(errors):
        lines += ["## Failed points", "", "| point | error |", "|---|---|"]
        for _, r in errors.head(50).iterrows():
            lines.append(f"| {r['point']} | {str(r['error']).replace('|', '/')} |")
        if len(errors) > 50:
            lines.append(f"| ... | {len(errors) - 50} more in the table |")
        lines.append("")
    return "\n".join(lines)


def write_plots(df, axes: dict, out_dir) -> list[Path]:
    """One PNG per axis (a panel per figure of ``FIGURES``) in ``out_dir``; returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    ran = df[df["error"].isna()] if len(df) else df
    for name, values in axes.items():
        col = INPUT_PREFIX + name
        if col not in ran or not len(ran):
            continue
        numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values) \
            and len(set(values)) > 1 and name not in ("seed", "family")
        groups = axis_groups(ran, name)
        ncols = 4
        nrows = math.ceil(len(FIGURES) / ncols)
        fig, axs = plt.subplots(nrows, ncols, figsize=(4.0 * ncols, 3.2 * nrows), squeeze=False)
        for ax, (fig_col, (label, kind)) in zip(axs.flat, FIGURES.items()):
            xs, meds = [], []
            for j, (lab, sub) in enumerate(groups):
                y = sub[fig_col].astype(float) if fig_col in sub else None
                if y is None:
                    continue
                x0 = float(sub[col].iloc[0]) if numeric else float(j)
                if kind == "number":
                    jitter = 0.0 if numeric else 0.08
                    rng = np.random.default_rng(j)
                    ax.plot(x0 + rng.uniform(-jitter, jitter, len(y)), y, ".", color="0.5", ms=4, alpha=0.6)
                finite = y.dropna()
                xs.append(x0)
                meds.append(float(np.median(finite)) if len(finite) and kind == "number"
                            else float(finite.mean()) if len(finite) else float("nan"))
            order = np.argsort(xs)
            ax.plot(np.asarray(xs)[order], np.asarray(meds)[order], "o-", color="tab:blue", ms=4,
                    label="median" if kind == "number" else "fraction")
            if not numeric:
                ax.set_xticks(range(len(groups)))
                ax.set_xticklabels([lab[:14] for lab, _ in groups], rotation=30, fontsize=7, ha="right")
            ax.set_title(label, fontsize=9)
            ax.grid(alpha=0.3)
        for ax in list(axs.flat)[len(FIGURES):]:
            ax.axis("off")
        fig.suptitle(f"against {name} ({len(ran)} points that ran)", fontsize=10)
        fig.tight_layout()
        safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in name)
        path = out_dir / f"sweep-{safe}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths
