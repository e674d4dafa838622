"""Identification strategies by name.

A strategy is a class (``Strategy``); a *preset* is one of them with other defaults, listed in
``PRESETS`` (name -> base class, the defaults it changes, why it exists) rather than written as a
subclass of its own.
"""
from .base import Sample, Strategy
from .bayes import BayesStrategy
from .gp import GpStrategy
from .mdipf import MdipfStrategy
from .nlls import NllsStrategy, fit_curve
from .observer_aware import NllsOaStrategy, ProposedOaStrategy
from .proposed import ProposedMu0Strategy, ProposedStrategy

#: name -> (base class, defaults it changes, what it is for)
PRESETS: dict[str, tuple[type[Strategy], dict, str]] = {
    "mdipf_raw": (MdipfStrategy, {"stabiliser": "raw", "prelim_solver": "trf"},
                  "MDIPF with the literal Theta (the raw correlation matrix, spectral radius up to P): beside "
                  "``mdipf`` to show what the stabilisation changes; literal in its prelim too (scipy's "
                  "trust-region solver)."),
    "proposed_raw": (ProposedStrategy, {"stabiliser": "raw", "box_halfwidth": [0.002, 0.01, 0.015],
                                        "prelim_solver": "trf"},
                     "The proposed strategy with the literal Theta; the box is what keeps the amplifying "
                     "transition in check, so it is tighter (the half-widths of the fewest corrections tried)."),
    "proposed_fast": (ProposedStrategy, {"filter_prelim_window": True, "publish_latest": True},
                      "Beyond the paper: correction 1 filters the preliminary fit's own window, so the first "
                      "J_EF and the confidence check come one window earlier (confirmation after 2 windows "
                      "instead of 3); it reports the filter's estimate after the confirmation window."),
    "proposed_latest": (ProposedStrategy, {"publish_latest": True},
                        "Beyond the paper: the proposed strategy reporting the filter's estimate after the "
                        "confirmation window (the candidate plus one more correction) instead of the candidate."),
}


def _preset(name: str, base: type[Strategy], changes: dict, doc: str) -> type[Strategy]:
    """The class of a preset: ``base`` with ``changes`` over its defaults (and its own name)."""
    return type(f"{base.__name__}[{name}]", (base,), {"name": name, "defaults": {**base.defaults, **changes},
                                                       "__doc__": doc, "__module__": base.__module__})


STRATEGIES: dict[str, type[Strategy]] = {cls.name: cls for cls in (
    NllsStrategy, MdipfStrategy, ProposedStrategy, ProposedMu0Strategy, NllsOaStrategy, ProposedOaStrategy,
    BayesStrategy, GpStrategy)}
STRATEGIES.update({name: _preset(name, *spec) for name, spec in PRESETS.items()})

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


__all__ = ["Sample", "Strategy", "BayesStrategy", "GpStrategy", "DEFAULT_STRATEGY", "NllsStrategy", "MdipfStrategy", "ProposedStrategy",
           "ProposedMu0Strategy", "NllsOaStrategy", "ProposedOaStrategy", "fit_curve", "PRESETS", "STRATEGIES",
           "make_strategy"]
