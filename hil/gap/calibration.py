"""What each grade of the answer has been worth: the fraction of right answers per grade that ``hil
bench gap --doc DIR`` measured on cases drawn at run time and wrote to ``DIR/gap-calibration.json``
(``CALIBRATION_FILE``; what "right" means per grade: ``hil.benchmarks.gap.grade_right``).  ``hil gap``
prints the line of its answer's grade beside the answer when the file exists (by default the
repository's ``docs/benchmarks``), so "confident" reads as "confident: right in 35 of 36 bench cases".
"""
from __future__ import annotations

import json
from pathlib import Path

CALIBRATION_FILE = "gap-calibration.json"
DEFAULT_PATH = Path(__file__).resolve().parents[2] / "docs" / "benchmarks" / CALIBRATION_FILE


def read_calibration(path=None) -> dict | None:
    """The calibration table written by the bench ({"seed", "cases", "grades": {grade: {"cases", "right",
    "fraction", "interval95"}}, ...}), or None when there is none (or it cannot be read as one)."""
    p = Path(path) if path is not None else DEFAULT_PATH
    try:
        table = json.loads(p.read_text())
    except (OSError, ValueError):     # no calibration file, or not JSON: the grade is said without one
        return None
    if not isinstance(table, dict) or not isinstance(table.get("grades"), dict):
        return None
    return dict(table, path=str(p))


def grade_line(confidence: str, table: dict | None) -> dict | None:
    """The calibration of one grade, for the answer's JSON (``which.calibration``): {grade, right, cases,
    fraction, seed, path, sentence}; None without a table or bench cases of that grade."""
    if not table:
        return None
    g = table["grades"].get(confidence)
    if not g or not g.get("cases"):
        return None
    return {"grade": confidence, "right": g["right"], "cases": g["cases"], "fraction": g.get("fraction"),
            "seed": table.get("seed"), "path": table["path"],
            "sentence": f"{confidence}: right in {g['right']} of {g['cases']} bench cases"}
