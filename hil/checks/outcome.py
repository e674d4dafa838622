"""Fail or error: who is to blame when a run goes wrong.

A test of a control unit has three outcomes besides a pass (the anchors: CANoe's Fail vs
ErrorInTestSystem, JUnit's ``<failure>`` vs ``<error>``):

- *fail* (``TcuFailed``, an AssertionError): the unit under test broke a check, fell silent or died
  (``PeerSilent``, exit 3 of ``hil run``), or its commands came late in periods the plant began on time;
- *error* (``hil.errors.BenchError``): the bench could not judge it -- the plant diverged
  (``PlantError``), the bus or the plant side died (any other exception), the log cannot be written or
  read, or the deadlines were missed because the plant itself began periods late
  (``missed_deadlines_plant_started_late``, or a CPU taken away by the machine);
- *skip*: the asked bus is not available here (``BusError`` at the start; the plugin makes it an error
  under ``CI=true``).

``hil.checks.judge`` judges checks under these verdicts: one judge for ``hil check``, ``require`` and the
pytest plugin.

``hil run``'s exit codes 3 and 5 each hold both sides; ``deadlines`` splits 5 by the summary's count of
periods the plant started late, ``run_error`` splits the exceptions of a run.  A silent TCU and a dead
bus look alike from the plant (both are silence): silence is blamed on the TCU.
"""
from __future__ import annotations

from ..errors import EXIT_DEADLINES, EXIT_SILENT, BenchError, HilError, LogError, PeerSilent, PlantError


class TcuFailed(AssertionError):
    """The unit under test failed outside any check: it fell silent or died, or its commands came late."""


def deadlines(summary: dict) -> TcuFailed | BenchError | None:
    """The verdict on a real-time run's missed deadlines: None within ``max_missed_fraction``; else
    ``TcuFailed`` when the misses in periods the plant began on time alone exceed it, ``BenchError`` when
    they exceed it only with the periods the plant itself began late (or lost its CPU)."""
    if not summary.get("deadlines_exceeded"):
        return None
    missed, steps = int(summary.get("missed_deadlines") or 0), int(summary.get("steps") or 0)
    allowed = float(summary.get("max_missed_fraction") or 0.0) * steps
    bench = min(missed, int(summary.get("missed_deadlines_plant_started_late") or 0)
                + int(summary.get("missed_deadlines_cpu_away") or 0))
    tcu = missed - bench
    if tcu > allowed:
        return TcuFailed(f"the TCU's commands came late: {tcu} of {steps} deadlines missed in periods the plant "
                         f"began on time, more than [bus] max_missed_fraction = {summary.get('max_missed_fraction'):g}"
                         " allows")
    return BenchError(f"the bench could not judge the TCU's timing: {missed} of {steps} deadlines missed, {bench} of "
                      "them in periods the plant itself began late or lost its CPU (a stall of the bench, not the TCU)",
                      EXIT_DEADLINES)


def run_error(error: BaseException) -> TcuFailed | BenchError:
    """The verdict on an exception a run raised (a ``BusError`` at the start is a skip: the caller's)."""
    if isinstance(error, PeerSilent):
        return TcuFailed(f"the TCU fell silent or died: {error}")
    if isinstance(error, PlantError):
        return BenchError(f"the bench could not judge: the plant failed: {error}", error.exit_code)
    if isinstance(error, HilError):
        return BenchError(f"the bench could not judge: {error}", error.exit_code)
    return BenchError(f"the bench could not judge: the run failed ({type(error).__name__}: {error})", EXIT_SILENT)


def recorded(run) -> TcuFailed | BenchError | None:
    """The verdict a log holds besides its checks (``hil check``): None for a run that finished within
    its deadlines; ``TcuFailed`` for a run the TCU's silence ended; ``BenchError`` for one that ended
    otherwise or whose plant began periods late; LogError for a damaged log."""
    log = run.log
    if log.damage:
        raise LogError(f"{run.path}: cannot judge a damaged log: {log.damage}")
    fault = (log.metadata.get("fault") or {}).get("reason")
    if fault:
        return TcuFailed(f"the TCU fell silent or died: {fault}")
    if log.ended_early:
        return BenchError(f"{run.path}: the run did not finish ({log.ended_early}): nothing to judge the TCU by")
    return deadlines(run.summary)

