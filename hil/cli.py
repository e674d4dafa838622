"""The ``hil`` command line.  Each sub-command lives in ``hil/commands/<name>.py`` and exposes
``register(subparsers)``; library code raises ``hil.errors.HilError`` and this module turns it into
one line on stderr and the error's exit code, never a traceback.  Nothing below imports this module."""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import signal
import sys
import threading

from . import commands
from .errors import EXIT_INTERRUPTED, HilError, caused_by_interrupt, remember_unraisable_interrupts


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hil", description="Hardware-in-the-loop testbench for railway traction: "
                                     "identify a wheelset's friction curve after a slipping fault.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


class _Interrupts:
    """The SIGINT handler of a whole command: raises ``KeyboardInterrupt`` and remembers that it
    did.  A library may swallow the interrupt while it imports (an optional import that catches the
    ImportError the interrupt became); the command still ends as interrupted: ``main`` looks after
    the imports and at the end, and ``hil.log.record.interrupts_between_writes`` before a run starts."""

    interrupted = False

    def __call__(self, signum, frame):
        self.interrupted = True
        raise KeyboardInterrupt


def main(argv=None) -> int:
    interrupts = _Interrupts()
    if threading.current_thread() is not threading.main_thread():
        return _main(argv, interrupts)
    signal.signal(signal.SIGINT, interrupts)
    previous = remember_unraisable_interrupts(lambda: setattr(interrupts, "interrupted", True))
    try:
        return _main(argv, interrupts)
    finally:
        sys.unraisablehook = previous


def _main(argv, interrupts: _Interrupts) -> int:
    try:
        # the imports (numpy, scipy, casadi ...) take about a second: a Ctrl-C then is an interrupt too
        parser = build_parser()
    except KeyboardInterrupt:
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:
        # a Ctrl-C inside an extension module's initialisation (e.g. scipy's HiGHS) comes out as
        # another error, "ImportError: initialization failed", caused by the KeyboardInterrupt
        if not caused_by_interrupt(e):
            raise
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if interrupts.interrupted:          # swallowed by an import
        print("hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    args = parser.parse_args(argv)
    try:
        code = int(args.func(args) or 0)
    except HilError as e:
        print(f"hil {args.command}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print(f"hil {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if interrupts.interrupted:          # swallowed on the way: the user asked to stop
        print(f"hil {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return code


if __name__ == "__main__":
    sys.exit(main())
