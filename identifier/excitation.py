"""A small open-loop torque excitation the TCU adds to its command in the slip's early stage.

Why: with the torque held, the friction curve is seen only along the one creep trajectory the slip
takes; a known torque wobble moves the creep around it, so the speed carries more information on
the curve per millisecond.  The excitation is a function of the step since the slip's detection and
of the run's seed only (never of a strategy's state), so the bench still feeds every strategy the
same samples, and a replay reproduces it.

    T_cmd(k) = T_demand (1 + a s(k))    for 0 <= k < duration_s / T, k = steps since the detected start
    T_cmd(k) = T_demand                 otherwise

with a = ``amplitude_fraction`` and s(k) in [-1, 1]:

    "sine":  s(k) = sin(2 pi f k T + phase),  phase = 2 pi x (x uniform from the seed)
    "prbs":  s(k) = +-1, a fresh sign from the seed every round(1 / (2 f T)) steps (a square wave of
             random sign at about f)

The defaults (amplitude 0) leave the command untouched.  ``[identifier.excitation]`` in a scenario
sets the fields (hil/config.py), e.g. ``amplitude_fraction = 0.03``, ``frequency_hz = 50``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

KINDS = ("sine", "prbs")
#: field -> (lowest, highest) accepted
RANGES = {"amplitude_fraction": (0.0, 0.5), "frequency_hz": (0.1, 1e5), "duration_s": (0.0, 3600.0)}


@dataclass(frozen=True)
class Excitation:
    amplitude_fraction: float = 0.0     # a, of the torque demand
    frequency_hz: float = 50.0          # f
    duration_s: float = 0.1             # how long after the detected slip start
    kind: str = "sine"

    @classmethod
    def from_dict(cls, table: dict) -> "Excitation":
        """From the ``[identifier.excitation]`` table; ValueError naming the field on bad input."""
        if not isinstance(table, dict):
            raise ValueError(f"excitation: must be a table, got {type(table).__name__}")
        unknown = set(table) - {"amplitude_fraction", "frequency_hz", "duration_s", "kind"}
        if unknown:
            raise ValueError(f"excitation: unknown key(s) {', '.join(sorted(unknown))} "
                             f"(known: amplitude_fraction, frequency_hz, duration_s, kind)")
        values = {}
        for key, (lo, hi) in RANGES.items():
            if key in table:
                x = table[key]
                if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
                    raise ValueError(f"excitation {key}: must be a number, got {x!r}")
                if not lo <= x <= hi:
                    raise ValueError(f"excitation {key}: must be in [{lo:g}, {hi:g}], got {x!r}")
                values[key] = float(x)
        if "kind" in table:
            if table["kind"] not in KINDS:
                raise ValueError(f"excitation kind: must be one of {', '.join(KINDS)}, got {table['kind']!r}")
            values["kind"] = table["kind"]
        return cls(**values)

    @property
    def active(self) -> bool:
        return self.amplitude_fraction > 0.0 and self.duration_s > 0.0

    def shape(self, steps_since_start: int, period_s: float, seed: int) -> float:
        """s(k) of the module docstring; 0 outside [0, duration)."""
        k = steps_since_start
        if not self.active or k < 0 or k * period_s >= self.duration_s:
            return 0.0
        if self.kind == "sine":
            phase = 2.0 * math.pi * _uniform(seed, 0)
            return math.sin(2.0 * math.pi * self.frequency_hz * k * period_s + phase)
        hold = max(1, round(1.0 / (2.0 * self.frequency_hz * period_s)))
        return 1.0 if _uniform(seed, 1 + k // hold) < 0.5 else -1.0

    def command_nm(self, demand_nm: float, step: int, detected_step: int | None, period_s: float,
                   seed: int) -> float:
        """The torque to command at ``step``: the demand, times 1 + a s(step - detected_step) once a
        slip has been detected (``detected_step``: its first step, None before)."""
        if detected_step is None or not self.active:
            return demand_nm
        return demand_nm * (1.0 + self.amplitude_fraction * self.shape(step - detected_step, period_s, seed))


def _uniform(seed: int, index: int) -> float:
    """A uniform number in [0, 1) from (seed, index) alone (the same on every machine and run)."""
    return float(np.random.default_rng([int(seed) & 0xFFFFFFFF, 7, index]).random())
