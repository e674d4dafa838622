"""What a person sees of a judged run: a figure per failed check, the suite's properties, and the JUnit
XML of ``hil check`` (the pytest plugin leaves its XML to pytest's ``--junitxml``).

A failed check's figure shows the signal over the run in its unit, its band (lo, hi) or threshold, the window
shaded and the first violation marked; a ``limit`` shows the summary's value against its bounds.  CI servers show a file named in a
``[[ATTACHMENT|path]]`` line of a test case's output (GitLab, Jenkins' JUnit attachments plugin).
"""
from __future__ import annotations

import hashlib
import math
import re
import socket
import time
import xml.etree.ElementTree as ET
from pathlib import Path


def properties(run) -> dict:
    """The suite's properties: the DBC's file name and digest (SHA-256 of the text the run used, as the
    pytest plugin hashes it), the package version that ran and the one that judged, the TCU under test,
    the log."""
    from importlib.metadata import PackageNotFoundError, version

    meta = run.log.metadata.get("dbc") or {}
    dbc = meta.get("text", "")
    try:
        judged_by = version("railway-hil")
    except PackageNotFoundError:  # a source tree, not installed: the report says unknown
        judged_by = "unknown"
    s = run.summary
    return {"dbc": meta.get("name", "none recorded"),
            "dbc_sha256": hashlib.sha256(dbc.encode()).hexdigest() if dbc else "none recorded",
            "railway_hil_version": (run.log.metadata.get("versions") or {}).get("railway-hil", "unknown"),
            "judged_by_version": judged_by,
            "tcu_under_test": f"{s.get('transport', '?')} ({s.get('strategy', '?')})"
            if s.get("transport") != "external" else "external",
            "bus": f"{s.get('bus', '?')} {s.get('mode', '?')}",
            "log": run.path}


def attachment(path) -> str:
    """The line CI servers read as a file attached to the test case."""
    return f"[[ATTACHMENT|{Path(path).resolve()}]]"


def figure(result, out_dir, stem: str = "") -> Path:
    """A PNG of a failed ``result`` in ``out_dir`` (its name from the check's): the signal over the run in
    its unit, the limit or threshold drawn, the window shaded, the first violation and the worst marked.
    A ``limit`` draws the summary's value against its bounds; a check that found no samples draws its
    bounds and says why.  ``responds`` draws the condition's signal with its threshold and, after each
    trigger, the span the condition had to hold within."""
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{stem}{'-' if stem else ''}{result.name}")[:120] + ".png"
    fig = draw(result)
    path = out_dir / name
    fig.savefig(path)
    plt.close(fig)
    return path


def draw(result):
    """The matplotlib figure of ``figure`` (one axes), not saved."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    plot = result.plot or {}
    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=90)
    unit = plot.get("unit", result.unit)
    t, v = plot.get("t", ()), plot.get("v", ())
    bounds = [(b, lab) for b, lab in ((result.lo, "lo"), (result.hi, "hi")) if b is not None and math.isfinite(b)]
    if "value" in plot:                       # a limit: one value of the run's summary against its bounds
        ax.plot([0.0], [plot["value"]], "o", color="C3" if not result.passed else "C0", ms=8,
                label=f"{result.signal} = {plot['value']:.6g}" + (f" {unit}" if unit else ""))
        ax.set_xlim(-1.0, 1.0)
        ax.set_xticks([])
        ax.set_xlabel("the run's summary")
    elif len(t):
        keep = plot.get("keep")
        ax.plot(t, v, lw=0.8, color="0.6" if keep is not None else "C0", label=plot.get("ylabel", result.signal))
        if keep is not None:
            ax.plot(t, np.where(keep, v, np.nan), lw=1.0, color="C0", label="judged")
        ax.set_xlabel("t (s)")
    else:                                     # nothing to draw but the bounds and why
        ax.text(0.5, 0.5, result.reason or "no samples", transform=ax.transAxes, ha="center", va="center",
                fontsize=8)
        ax.set_xlabel("t (s)")
    for bound, lab in bounds:
        ax.axhline(bound, color="C2", ls="--", lw=0.9, label=f"{lab} {bound:g}" + (f" {result.unit}" if result.unit else ""))
    if "threshold" in plot:                   # responds: the condition's threshold, the span after each trigger
        op, value = plot["threshold"]
        ax.axhline(value, color="C2", ls="--", lw=0.9, label=f"condition {op} {value:g}" + (f" {unit}" if unit else ""))
        for tt in plot.get("triggers", ()):
            ax.axvspan(tt, tt + plot["within_s"], color="C1", alpha=0.15)
        if len(plot.get("triggers", ())):
            ax.axvspan(np.nan, np.nan, color="C1", alpha=0.15, label=f"within {plot['within_s'] * 1e3:g} ms")
    else:
        for tt in plot.get("triggers", ()):
            ax.axvline(tt, color="C1", lw=0.8)
    if result.window_s is not None and len(t):
        t0, t1 = result.window_s
        ax.axvspan(t0, min(t1, float(t[-1])) if math.isfinite(t1) else float(t[-1]), color="C1", alpha=0.12,
                   label="window")
    if plot.get("marks", True) and len(t):
        if result.first is not None and result.first[0] is not None and math.isfinite(result.first[1]):
            ax.plot([result.first[0]], [result.first[1]], "o", color="C3", ms=6, label="first violation")
        if result.worst is not None and result.worst[0] is not None and math.isfinite(result.worst[1]):
            ax.plot([result.worst[0]], [result.worst[1]], "x", color="C3", ms=7, label="worst")
    ax.set_ylabel(f"{plot.get('ylabel', result.signal)}" + (f" ({unit})" if unit else ""))
    ax.set_title(result.line(), fontsize=7, loc="left", wrap=True)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    return fig


def junit_xml(suite_name: str, results: list, props: dict, path, verdict=None, attachments: dict | None = None,
              seconds: float = 0.0, errored=()) -> None:
    """Write the JUnit XML of one judged log: a test case per check (``<failure>`` with its line; a run the
    TCU's verdict failed has each check failed with it, ``judge.judged``), and for a run the bench broke
    (``verdict`` a ``BenchError``) each check named in ``errored`` an ``<error>``, as the pytest plugin
    reports them."""
    attachments = attachments or {}
    cases = [(name, "error", str(verdict), None) for name in errored]
    for r in results:
        cases.append((r.name, None if r.passed else "failure", r.line(), attachments.get(id(r))))
    failures = sum(1 for _, k, _, _ in cases if k == "failure")
    errors = sum(1 for _, k, _, _ in cases if k == "error")
    root = ET.Element("testsuites", name="hil check", tests=str(len(cases)), failures=str(failures),
                      errors=str(errors), time=f"{seconds:.3f}")
    suite = ET.SubElement(root, "testsuite", name=suite_name, tests=str(len(cases)), failures=str(failures),
                          errors=str(errors), skipped="0", time=f"{seconds:.3f}",
                          timestamp=time.strftime("%Y-%m-%dT%H:%M:%S"), hostname=socket.gethostname())
    pe = ET.SubElement(suite, "properties")
    for k, v in props.items():
        ET.SubElement(pe, "property", name=k, value=str(v))
    for name, kind, line, png in cases:
        case = ET.SubElement(suite, "testcase", classname=suite_name, name=name, time="0.000")
        if kind is not None:
            ET.SubElement(case, kind, message=line, type=kind).text = line
        out = [line] + ([attachment(png)] if png else [])
        ET.SubElement(case, "system-out").text = "\n".join(out)
    ET.ElementTree(root).write(str(path), encoding="utf-8", xml_declaration=True)
