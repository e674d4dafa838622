"""Fault stages from the true states: normal, early (stable side), serious (past the peak)."""
from __future__ import annotations

import math

NORMAL, EARLY, SERIOUS = "normal", "early", "serious"


class StageTracker:
    """Tracks t_f, t_serious (first crossing of the fault curve's peak creep) and T_det."""

    def __init__(self, fault_time_s: float, fault_peak_creep_kmh: float):
        self.fault_time_s = fault_time_s
        self.peak_creep_kmh = fault_peak_creep_kmh
        self.serious_time_s: float | None = None

    def update(self, t_s: float, creep_speed_kmh: float) -> str:
        if t_s < self.fault_time_s:
            return NORMAL
        if self.serious_time_s is None and creep_speed_kmh >= self.peak_creep_kmh:
            self.serious_time_s = t_s
        return EARLY if self.serious_time_s is None else SERIOUS

    @property
    def deterioration_time_s(self) -> float:
        """T_det = t_serious - t_f (NaN until the serious stage is reached)."""
        if self.serious_time_s is None:
            return math.nan
        return self.serious_time_s - self.fault_time_s
