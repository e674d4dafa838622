"""Physical parameters of the wheelset-rail system (paper Table 1) and derived quantities."""
from __future__ import annotations

from dataclasses import dataclass

KMH_PER_MS = 3.6


@dataclass(frozen=True)
class WheelsetParams:
    """Table 1 of the paper, plus the train-level data a full plant needs.

    Units are SI unless the name says otherwise.
    """

    axle_load_kg: float = 13_500.0          # T_W, axle load of the faulty wheelset
    motor_inertia_kgm2: float = 6.0         # J_m
    wheelset_inertia_kgm2: float = 80.0     # J_d
    wheel_radius_m: float = 0.4375          # r
    train_mass_kg: float = 408_000.0        # M
    gravity_ms2: float = 9.8                # g
    gear_ratio: float = 2.788               # R_g
    efficiency: float = 0.97                # eta
    half_bogie_distance_m: float = 19.0     # L   (axle load transfer only)
    half_wheelbase_m: float = 2.5           # L_b (axle load transfer only)
    coupler_height_m: float = 0.88          # Z   (axle load transfer only)
    bogie_height_m: float = 2.6             # z   (axle load transfer only)
    # Not in Table 1: the train is pulled by this many driven axles.  The other axles are assumed
    # to hold the demanded adhesion, so the faulty one barely changes the train speed.
    driven_axles: int = 16
    # Davis running resistance R(v) = a + b*v + c*v^2 [N], v in m/s.
    davis_a_n: float = 2_600.0
    davis_b_n_per_ms: float = 350.0
    davis_c_n_per_ms2: float = 70.0

    @property
    def equivalent_inertia_kgm2(self) -> float:
        """J_eq = J_m + J_d / (eta * R_g^2), referred to the motor shaft (Appendix A)."""
        return self.motor_inertia_kgm2 + self.wheelset_inertia_kgm2 / (self.efficiency * self.gear_ratio ** 2)

    @property
    def normal_force_n(self) -> float:
        """T_W * g."""
        return self.axle_load_kg * self.gravity_ms2

    @property
    def torque_per_mu_nm(self) -> float:
        """Motor-shaft load torque per unit friction coefficient: T_L = mu * this (eq. 5)."""
        return self.normal_force_n * self.wheel_radius_m / (self.efficiency * self.gear_ratio)

    def running_resistance_n(self, train_speed_ms):
        v = train_speed_ms
        return self.davis_a_n + self.davis_b_n_per_ms * v + self.davis_c_n_per_ms2 * v * v
