"""Identification strategies by name."""
from .base import Sample, Strategy
from .nlls import NllsStrategy, fit_curve

STRATEGIES: dict[str, type[Strategy]] = {NllsStrategy.name: NllsStrategy}


def make_strategy(name: str, settings, seed: int = 0) -> Strategy:
    try:
        cls = STRATEGIES[name]
    except KeyError:
        raise ValueError(f"unknown strategy {name!r}; available: {', '.join(sorted(STRATEGIES))}") from None
    return cls(settings, seed)


__all__ = ["Sample", "Strategy", "NllsStrategy", "fit_curve", "STRATEGIES", "make_strategy"]
