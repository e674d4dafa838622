"""Identification strategies by name."""
from .base import Sample, Strategy
from .bayes import BayesStrategy
from .mdipf import MdipfRawStrategy, MdipfStrategy
from .nlls import NllsStrategy, fit_curve
from .observer_aware import NllsOaStrategy, ProposedOaStrategy
from .proposed import (ProposedFastStrategy, ProposedLatestStrategy, ProposedMu0Strategy, ProposedRawStrategy,
                       ProposedStrategy)

STRATEGIES: dict[str, type[Strategy]] = {cls.name: cls for cls in (
    NllsStrategy, MdipfStrategy, ProposedStrategy, MdipfRawStrategy, ProposedRawStrategy, ProposedMu0Strategy,
    ProposedFastStrategy, ProposedLatestStrategy, NllsOaStrategy, ProposedOaStrategy, BayesStrategy)}

#: the strategy the README recommends to users (intervals, confirms only what the data support)
RECOMMENDED = "bayes"


def make_strategy(name: str, settings, seed: int = 0) -> Strategy:
    try:
        cls = STRATEGIES[name]
    except KeyError:
        raise ValueError(f"unknown strategy {name!r}; available: {', '.join(sorted(STRATEGIES))}") from None
    return cls(settings, seed)


__all__ = ["Sample", "Strategy", "BayesStrategy", "RECOMMENDED", "NllsStrategy", "MdipfStrategy", "ProposedStrategy", "ProposedMu0Strategy",
           "ProposedFastStrategy", "ProposedLatestStrategy", "NllsOaStrategy", "ProposedOaStrategy", "MdipfRawStrategy", "ProposedRawStrategy", "fit_curve", "STRATEGIES", "make_strategy"]
