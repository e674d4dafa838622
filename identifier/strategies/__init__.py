"""Identification strategies by name.

A strategy is a class (``Strategy``); a *preset* is one of them with other defaults, listed in
``PRESETS`` (name -> base strategy's name, the defaults it changes, why it exists) rather than written as a
subclass of its own.

The classes are listed in a table (``BACKENDS``: name -> module, class), as python-can lists its
interfaces, and a strategy's module is imported when its class is first asked for (``STRATEGIES[name]``,
``make_strategy``, or a class name from this package).  Why: most strategies fit with scipy.optimize,
whose import costs about 0.4 s, and the processes that never identify (the plant, ``hil check``, ``hil
view``, the CLI's help) need the names only.  A TCU imports its strategy's module when it makes the
strategy, before its first period.
"""
from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping

from .base import Sample, Strategy

#: name -> (module in this package, class): the strategies, imported on first use
BACKENDS: dict[str, tuple[str, str]] = {
    "nlls": ("nlls", "NllsStrategy"),
    "mdipf": ("mdipf", "MdipfStrategy"),
    "proposed": ("proposed", "ProposedStrategy"),
    "proposed_mu0": ("proposed", "ProposedMu0Strategy"),
    "nlls_oa": ("observer_aware", "NllsOaStrategy"),
    "proposed_oa": ("observer_aware", "ProposedOaStrategy"),
    "bayes": ("bayes", "BayesStrategy"),
    "gp": ("gp", "GpStrategy"),
}

#: name -> (base strategy, defaults it changes, what it is for)
PRESETS: dict[str, tuple[str, dict, str]] = {
    "mdipf_raw": ("mdipf", {"stabiliser": "raw", "prelim_solver": "trf"},
                  "MDIPF with the literal Theta (the raw correlation matrix, spectral radius up to P): beside "
                  "``mdipf`` to show what the stabilisation changes; literal in its prelim too (scipy's "
                  "trust-region solver)."),
    "proposed_raw": ("proposed", {"stabiliser": "raw", "box_halfwidth": [0.002, 0.01, 0.015],
                                  "prelim_solver": "trf"},
                     "The proposed strategy with the literal Theta; the box is what keeps the amplifying "
                     "transition in check, so it is tighter (the half-widths of the fewest corrections tried)."),
    "proposed_fast": ("proposed", {"filter_prelim_window": True, "publish_latest": True},
                      "Beyond the paper: correction 1 filters the preliminary fit's own window, so the first "
                      "J_EF and the confidence check come one window earlier (confirmation after 2 windows "
                      "instead of 3); it reports the filter's estimate after the confirmation window."),
    "proposed_latest": ("proposed", {"publish_latest": True},
                        "Beyond the paper: the proposed strategy reporting the filter's estimate after the "
                        "confirmation window (the candidate plus one more correction) instead of the candidate."),
}

#: the other names this package gives (module in this package, name there), imported on first use
_LAZY_NAMES = {cls: (module, cls) for module, cls in BACKENDS.values()}
_LAZY_NAMES["fit_curve"] = ("nlls", "fit_curve")


def _load(module: str, name: str):
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


def _preset(name: str, base: type[Strategy], changes: dict, doc: str) -> type[Strategy]:
    """The class of a preset: ``base`` with ``changes`` over its defaults (and its own name)."""
    return type(f"{base.__name__}[{name}]", (base,), {"name": name, "defaults": {**base.defaults, **changes},
                                                       "__doc__": doc, "__module__": base.__module__})


class _Strategies(Mapping):
    """name -> strategy class (``BACKENDS``, then ``PRESETS``); a class is imported (a preset made) the first
    time it is asked for and the same object returned after.  Names, ``in`` and ``len`` import nothing."""

    def __init__(self):
        self._classes: dict[str, type[Strategy]] = {}

    def __getitem__(self, name: str) -> type[Strategy]:
        cls = self._classes.get(name)
        if cls is None:
            if name in BACKENDS:
                cls = _load(*BACKENDS[name])
            elif name in PRESETS:
                base, changes, doc = PRESETS[name]
                cls = _preset(name, self[base], changes, doc)
            else:
                raise KeyError(name)
            self._classes[name] = cls
        return cls

    def __iter__(self) -> Iterator[str]:
        yield from BACKENDS
        yield from PRESETS

    def __len__(self) -> int:
        return len(BACKENDS) + len(PRESETS)

    def __contains__(self, name) -> bool:
        return name in BACKENDS or name in PRESETS

    def __repr__(self) -> str:
        return f"STRATEGIES({', '.join(self)})"


STRATEGIES = _Strategies()

#: the default strategy, and the one recommended: it gives intervals, confirms only what the data
#: support and assumes no curve form (the identification guide compares it with the others). ``hil run``,
#: ``hil tcu``, replay of a log that names none, sweeps and the TCU all take it from here.
DEFAULT_STRATEGY = "gp"


def make_strategy(name: str, settings, seed: int = 0) -> Strategy:
    try:
        cls = STRATEGIES[name]
    except KeyError:
        raise ValueError(f"unknown strategy {name!r}; available: {', '.join(sorted(STRATEGIES))}") from None
    return cls(settings, seed)


def __getattr__(name: str):
    """A strategy class (or ``fit_curve``) by its name in this package, imported on first use."""
    if name in _LAZY_NAMES:
        value = _load(*_LAZY_NAMES[name])
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Sample", "Strategy", "BayesStrategy", "GpStrategy", "DEFAULT_STRATEGY", "NllsStrategy", "MdipfStrategy", "ProposedStrategy",
           "ProposedMu0Strategy", "NllsOaStrategy", "ProposedOaStrategy", "fit_curve", "BACKENDS", "PRESETS", "STRATEGIES",
           "make_strategy"]
