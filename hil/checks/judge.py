"""The one judge: checks judged over a run under the run's own verdict, for ``hil check``
(``hil.checks.offline``), ``require`` and the pytest plugin alike, so that a log gets the same verdict per
check whoever judges it.

A run whose own verdict is a fail (``hil.checks.outcome``: the TCU fell silent, died or came late) fails
*every* check, whatever the check found on the part that was recorded: a check judged on part of a run
says nothing of the rest (a cycle time measured on a TCU's frames up to its freeze would pass), and a
pass there would be a confident wrong answer.  A run the bench broke (``BenchError``) is an error for
every check: nothing is judged.
"""
from __future__ import annotations

import dataclasses

from ..errors import BenchError, ConfigError
from .kinds import Check, Result
from .outcome import recorded
from .run import Run, as_run


def judged(checks, run, verdict=None) -> list:
    """Every check's result over ``run`` under the run's own ``verdict`` (``outcome.recorded`` of its log, or
    what the run raised): the one judge of ``hil check``, ``require`` and the pytest plugin.

    ``verdict`` None: each check as it found.  ``TcuFailed``: each check fails with the verdict as its reason
    (its note says what it found on what was recorded).  ``BenchError``: raised, nothing is judged.  A
    ``ConfigError`` of a check (a signal the log does not have) names the check where it was written."""
    if isinstance(verdict, BenchError):
        raise verdict
    results = []
    for check in checks:
        try:
            r = check(run)
        except ConfigError as e:
            if verdict is None:
                raise ConfigError(f"{check.where}: {e}" if check.where else str(e)) from None
            # the part recorded lacks what the check names (an event of a summary the run never wrote): the
            # run's verdict stands, as it does for every check of that run
            fields = check.fields()
            r = Result(check.name, check.kind, next((str(fields[k]) for k in ("signal", "key", "frame", "condition")
                                                    if fields.get(k)), ""), "", "", "", passed=False, req=check.req, verb="",
                       reason=str(verdict), note=f"on the part recorded it could not be judged: {e}")
            results.append(r)
            continue
        if verdict is not None:
            seen = "held" if r.passed else "failed too"
            r = dataclasses.replace(r, passed=False, reason=str(verdict),
                                    note=f"on the part recorded it {seen}" + (f"; {r.note}" if r.note else ""))
        results.append(r)
    return results


# -- require -----------------------------------------------------------------------------------------------
class CheckFailed(AssertionError):
    """One or more checks failed; ``results`` holds every result (passed ones too), the message one line
    per failed check."""

    def __init__(self, results: list[Result], run: Run | None = None, checks: tuple = (), verdict=None):
        self.results, self.run, self.checks, self.verdict = results, run, tuple(checks), verdict
        failed = [r for r in results if not r.passed]
        # a run the TCU failed: its verdict first (every check failed with it, ``judged``)
        head = str(verdict) if verdict is not None else f"{len(failed)} of {len(results)} checks failed:"
        lines = [head] + [f"  {r.line()}" for r in failed]
        super().__init__("\n".join(lines))


def require(run, *checks: Check) -> list[Result]:
    """Judge every check over ``run`` (a ``Run`` or a log's path) under the verdict its log records, by the
    judge ``hil check`` uses (``judged``: a TCU that fell silent fails every check, a run
    the bench broke raises its ``BenchError``); ``CheckFailed`` (an AssertionError) listing every failed
    one, else the results."""
    __tracebackhide__ = True                  # pytest: the failure points at the test's line, not here
    run = as_run(run)
    verdict = recorded(run)
    results = judged(checks, run, verdict)
    if not all(r.passed for r in results):
        raise CheckFailed(results, run, checks, verdict)
    return results
