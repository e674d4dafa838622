"""``hil bench NAME``: benchmarks that print their figures.  Each lives in
``hil/benchmarks/<name>.py`` (or the package ``<name>/``) with ``register(subparsers)``; modules without it
are helpers."""
from __future__ import annotations

import importlib
import pkgutil

from .. import benchmarks


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (speed and accuracy figures)")
    bsub = p.add_subparsers(dest="benchmark", metavar="BENCHMARK")
    bsub.required = True
    for info in sorted(pkgutil.iter_modules(benchmarks.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{benchmarks.__name__}.{info.name}")
        if hasattr(module, "register"):          # helper modules (e.g. judge) register no command
            module.register(bsub)
