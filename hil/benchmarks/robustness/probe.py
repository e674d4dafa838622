"""A probe's record: its figures, its cases' failures and its verdict, the one shape every part of
``hil bench robustness`` returns.
"""
from __future__ import annotations

import time

#: a run that takes longer than this is a hang
RUN_TIMEOUT_S = 300.0


def short(text: str, n: int = 300) -> str:
    """``text`` on one line, cut to ``n`` characters (a failure's record stays readable)."""
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[:n - 3] + "..."


class Part:
    """A part's figures, its cases' failures and its verdict."""

    def __init__(self, name: str, seed: int, target: str):
        self.name, self.seed, self.target = name, seed, target
        self.figures: dict = {}
        self.failures: list[dict] = []
        self.cases = 0
        self.t0 = time.monotonic()

    def fail(self, case, what: str, detail: str) -> None:
        self.failures.append({"case": case, "what": short(what, 200), "detail": short(detail, 600)})

    def done(self, passed: bool | None = None) -> dict:
        ok = not self.failures if passed is None else (passed and not self.failures)
        return {"part": self.name, "cases": self.cases, "target": self.target, "passed": ok,
                "figures": self.figures, "failures": self.failures, "wall_s": round(time.monotonic() - self.t0, 1)}
