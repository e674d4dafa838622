"""One exception tree for the whole ``hil`` package, each class carrying the exit code the command
line ends with.  Library code raises these; ``hil.cli`` catches ``HilError`` once, prints its one-line
message and exits with ``exit_code``.  Nothing here imports anything else of the project.

    HilError                exit 2   something the user can fix (the base)
      ConfigError           exit 2   a scenario file, a table, a --set or --out value
        ScenarioMismatch    exit 2   the TCU announces another scenario than the plant's (before step 0)
      BusError              exit 2   a bus that cannot be opened here
      LogError              exit 2   a file that is not a log this tool reads
      PlantError            exit 2   an FMU or plant that cannot be loaded or run
      LogWriteError         exit 2   the log cannot be written (disk full, file size limit, I/O error)
      ClusterError          exit 2   a Dask cluster that cannot be started or reached (hil sweep)
      PeerSilent            exit 3   the other side of the bus fell silent or died mid-run
      TcuDidNotStart        exit 3   the TCU process this run watches ended before it joined the bus
        NoProgress          exit 3   (lockstep) the other side lives but the pending step gets no answer
      PlantFault            exit 4   (TCU side) the plant reported a fault
      DeadlinesMissed       exit 5   (real time) more deadlines missed than [bus] max_missed_fraction allows
      BenchError            exit 2, 3 or 5 (its cause's)   the bench could not judge the unit under test
                                     (hil check, the pytest plugin: an *error*, never a *fail*)
"""
from __future__ import annotations

import sys

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_SILENT = 3
EXIT_PLANT_FAULT = 4
EXIT_DEADLINES = 5
EXIT_INTERRUPTED = 130


class HilError(Exception):
    """An error whose message is one line a user can act on."""
    exit_code = EXIT_USAGE


class ConfigError(HilError, ValueError):
    """A scenario, table or command-line value that cannot be used; the message names file and field."""


class ScenarioMismatch(ConfigError):
    """The TCU on the bus runs another scenario than the plant (their digests differ, ``TcuScenario``):
    found before the first period; the message names both digests."""


#: the name the scenario loader's errors have always had
ScenarioError = ConfigError


class BusError(HilError, ValueError):
    """A bus spec that names nothing usable here; the message names the bus and what is available."""


class LogError(HilError, ValueError):
    """A file that is not a log this tool can read."""


class LogWriteError(HilError, RuntimeError):
    """Writing the run's log failed (disk full, file size limit, I/O error); the message names the file
    and how far it got.  The run stops, its cleanup still completes."""


class PlantError(HilError, ValueError):
    """A plant (an FMU, its mapping or parameters) that cannot be loaded or run."""


class ClusterError(HilError, RuntimeError):
    """A Dask cluster that cannot be started or reached, or a sweep that could not finish its points."""


class PeerSilent(HilError, RuntimeError):
    """The other side of the bus stopped sending (or its process ended) during a run."""
    exit_code = EXIT_SILENT


class TcuDidNotStart(HilError, RuntimeError):
    """The TCU process a run started or watches ended before it sent a frame: a command that does not run
    (a typo, a missing module), an error of the set-up rather than a failure of the unit (``hil.checks.
    outcome``); the message gives its exit code and the last lines of its stderr."""
    exit_code = EXIT_SILENT


class NoProgress(PeerSilent):
    """Lockstep: the TCU keeps its heartbeat but the step the plant waits for gets no command (the
    sensor frame rejected or lost, or the TCU moved to another step); the message names the step and
    the likely cause."""


class PlantFault(HilError, RuntimeError):
    """The TCU was told by the plant's heartbeat that the plant side failed."""
    exit_code = EXIT_PLANT_FAULT


class DeadlinesMissed(HilError, RuntimeError):
    """A real-time run completed (logs written) but missed more deadlines than the scenario's
    ``[bus] max_missed_fraction`` allows; the message gives how many of how many."""
    exit_code = EXIT_DEADLINES


class BenchError(HilError, RuntimeError):
    """The bench, not the unit under test, failed: the plant diverged, the bus or the plant side died, or
    the plant itself began periods past their deadlines.  A test verdict then is an *error* (the unit
    could not be judged), never a *fail* (``hil.checks.outcome``).  ``exit_code`` is its cause's."""

    def __init__(self, message: str, exit_code: int = EXIT_USAGE):
        super().__init__(message)
        self.exit_code = exit_code


def caused_by_interrupt(error: BaseException) -> bool:
    """``error`` is, or was caused by, a ``KeyboardInterrupt`` (its ``__cause__``/``__context__``
    chain): an extension module that catches the interrupt raised in it re-raises it as another
    error (scipy's HiGHS initialisation: "ImportError: initialization failed").  The commands end
    such an error as interrupted, not with a traceback."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return False


def remember_unraisable_interrupts(remember):
    """Install a ``sys.unraisablehook`` and return the hook it replaces.  Under it an interrupt raised
    where Python cannot pass it on (a signal handler's ``KeyboardInterrupt`` landing inside a ctypes
    callback, such as llvmlite's object-cache hook while numba compiles, or in a ``__del__``) calls
    ``remember()`` instead of printing "Exception ignored in ... Traceback"; any other unraisable
    error goes to the default hook.  The command then ends as interrupted from what ``remember``
    recorded."""
    def hook(hook_args) -> None:
        if isinstance(hook_args.exc_value, KeyboardInterrupt):
            remember()
            return
        sys.__unraisablehook__(hook_args)
    previous, sys.unraisablehook = sys.unraisablehook, hook
    return previous
