"""Speed sensors: what a TCU really gets from the plant (seeded noise, optional quantisation)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorConfig:
    motor_speed_noise_rad_s: float = 0.0     # standard deviation of white noise
    train_speed_noise_ms: float = 0.0
    motor_speed_quantum_rad_s: float = 0.0   # 0 = no quantisation
    train_speed_quantum_ms: float = 0.0


class SensorModel:
    def __init__(self, cfg: SensorConfig, seed: int):
        self.cfg = cfg
        self._rng = np.random.default_rng(seed)

    @staticmethod
    def _quantise(value: float, quantum: float) -> float:
        return value if quantum <= 0 else float(np.round(value / quantum) * quantum)

    def measure(self, motor_speed_rad_s: float, train_speed_ms: float) -> tuple[float, float]:
        """(measured motor speed rad/s, measured train speed m/s)."""
        noise_omega, noise_v = self._rng.standard_normal(2).tolist()     # Python floats: the same numbers
        omega = motor_speed_rad_s + self.cfg.motor_speed_noise_rad_s * noise_omega
        v = train_speed_ms + self.cfg.train_speed_noise_ms * noise_v
        return (self._quantise(omega, self.cfg.motor_speed_quantum_rad_s),
                self._quantise(v, self.cfg.train_speed_quantum_ms))
