"""What a person sees of a judged run: a figure per failed check, the suite's properties, and the JUnit
XML of ``hil check`` (the pytest plugin leaves its XML to pytest's ``--junitxml``).

A failed check's figure shows the signal over the run, its band (lo, hi), the window shaded and the first
violation marked; a ``limit`` (one value of the summary) has none.  CI servers show a file named in a
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
    except PackageNotFoundError:
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


def figure(result, out_dir, stem: str = "") -> Path | None:
    """A PNG of a failed ``result`` in ``out_dir`` (its name from the check's); None for a check without
    a signal over time (``limit``) or without samples."""
    plot = result.plot
    if not plot or len(plot.get("t", ())) == 0:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{stem}{'-' if stem else ''}{result.name}")[:120] + ".png"
    fig, ax = plt.subplots(figsize=(8, 3.2), dpi=90)
    t, v = plot["t"], plot["v"]
    keep = plot.get("keep")
    ax.plot(t, v, lw=0.8, color="0.6" if keep is not None else "C0", label=result.signal)
    if keep is not None:
        import numpy as np
        ax.plot(t, np.where(keep, v, np.nan), lw=1.0, color="C0", label="judged")
    for bound in (result.lo, result.hi):
        if bound is not None and math.isfinite(bound):
            ax.axhline(bound, color="C2", ls="--", lw=0.9)
    if result.window_s is not None:
        t0, t1 = result.window_s
        ax.axvspan(t0, min(t1, float(t[-1])) if math.isfinite(t1) else float(t[-1]), color="C1", alpha=0.12,
                   label="window")
    for tt in plot.get("triggers", ()):
        ax.axvline(tt, color="C1", lw=0.8)
    if result.first is not None and result.first[0] is not None and math.isfinite(result.first[1]):
        ax.plot([result.first[0]], [result.first[1]], "o", color="C3", ms=6, label="first violation")
    if result.worst is not None and result.worst[0] is not None and math.isfinite(result.worst[1]):
        ax.plot([result.worst[0]], [result.worst[1]], "x", color="C3", ms=7, label="worst")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"{result.signal}" + (f" ({result.unit})" if result.unit else ""))
    ax.set_title(result.line(), fontsize=7, loc="left", wrap=True)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    path = out_dir / name
    fig.savefig(path)
    plt.close(fig)
    return path


def junit_xml(suite_name: str, results: list, props: dict, path, verdict=None, attachments: dict | None = None,
              seconds: float = 0.0) -> None:
    """Write the JUnit XML of one judged log: a test case per check (``<failure>`` with its line), and a
    ``run`` case for a verdict outside the checks (``TcuFailed``: a failure; ``BenchError``: an error)."""
    from .outcome import TcuFailed

    attachments = attachments or {}
    cases = []
    if verdict is not None:
        cases.append(("run", "failure" if isinstance(verdict, TcuFailed) else "error", str(verdict), None))
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
