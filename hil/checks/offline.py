"""Judging a recorded log against a checks file, apart from the run (``hil check LOG CHECKS.toml``).

The log is read once (``Run.open``), its recorded verdict taken first (``outcome.recorded``), then every
check of the file is judged under it by the one judge the pytest plugin and ``require`` use too
(``judge.judged``): a TCU that fell silent, died or came late fails every check; a run the bench broke
is an error for every check and is not judged further.  With a
JUnit path, the XML is written and each failed check gets its figure beside it (``NAME-figures/``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import BenchError, ConfigError
from .outcome import TcuFailed, recorded
from .report import figure, junit_xml, properties
from .run import Run, open_can_log
from .spec import judge, load_checks


@dataclass
class Judgement:
    """What ``hil check`` found: ``results`` per check, ``verdict`` outside them (``TcuFailed``,
    ``BenchError`` or None), the figures of failed checks (result id -> path)."""
    results: list
    verdict: object = None
    figures: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def passed(self) -> bool:
        return self.verdict is None and all(r.passed for r in self.results)


def check_log(log_path, checks_path, junitxml=None, dbc=None) -> Judgement:
    """Judge the log at ``log_path`` by the checks file ``checks_path``; ConfigError for a bad checks
    file, LogError for a log that cannot be read.  A rig's CAN log (a python-can format, by its suffix) is
    decoded with ``dbc`` (default: the HIL's own ``hil/hil.dbc``)."""
    from ..replay import CAN_LOG_SUFFIXES

    suite = load_checks(checks_path)          # a bad file is reported before the log is read
    t0 = time.perf_counter()
    if Path(log_path).suffix.lower() in CAN_LOG_SUFFIXES:
        run = open_can_log(log_path, dbc or Path(__file__).resolve().parents[1] / "hil.dbc")
    else:
        run = Run.open(log_path)
        if dbc is not None:
            raise ConfigError(f"--dbc {dbc}: only for a rig's CAN log; an MCAP log of hil run keeps its own DBC")
    verdict = recorded(run)
    results = [] if isinstance(verdict, BenchError) else judge(suite, run, verdict)
    seconds = time.perf_counter() - t0
    out = Judgement(results, verdict, seconds=seconds)
    if junitxml is not None:
        junit = Path(junitxml)
        stem = Path(checks_path).stem
        for r in results:
            if not r.passed:
                png = figure(r, junit.with_name(f"{junit.stem}-figures"), stem)
                if png is not None:
                    out.figures[id(r)] = png
        junit_xml(stem, results, properties(run), junit, verdict, out.figures, seconds,
                  errored=[c.name for c in suite.checks] if isinstance(verdict, BenchError) else ())
    return out


__all__ = ["Judgement", "TcuFailed", "check_log"]
