"""Everything the TCU knows before a run: the nominal vehicle model and the identifier's tuning.

The TCU knows the vehicle's nominal parameters (it needs them to turn an estimated load torque
into a friction coefficient) and the normal rail curve NFCC-0 it was running on; it never knows
the fault curve or the fault time.
"""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class VehicleModel:
    equivalent_inertia_kgm2: float
    torque_per_mu_nm: float        # T_L = mu * this
    gear_ratio: float
    wheel_radius_m: float


@dataclass(frozen=True)
class IdentifierSettings:
    period_s: float                               # sampling (= bus exchange) period
    vehicle: VehicleModel
    torque_demand_nm: float                       # the traction torque the TCU commands
    initial_guess: tuple[float, ...]              # theta used before any fit (NFCC-0 by default)
    # The observer pole and the settle time trade the observer's noise against its transient after
    # the fault: settle = 4/p leaves (1 + pt) e^-pt = 9 % of the transient.  A faster pole settles
    # sooner but is noisier; the trade-off measured for these defaults: docs/design/identifier.md.
    observer_pole_rad_s: float = 500.0            # double pole p of the load-torque observer (rad/s)
    lag_compensation: bool = True                 # pair mu^(k) with v_s(k - 2/(pT))
    detection_creep_rise_kmh: float = 0.03        # creep above its pre-fault mean that flags a slip
    baseline_samples: int = 50                    # samples averaged for the pre-fault creep mean
    settle_time_s: float = 0.008                  # samples skipped after detection (observer transient: 4/p, above)
    window_samples: int = 6                       # L, samples per correction window (the least above 2n+1 = 5)
    k_pe: float = 1e-4                            # K_PE, preliminary-evaluation threshold on J_EF
    c_lw: float = 3.0                             # lower confidence coefficient
    c_up: float = 3.0                             # upper confidence coefficient
    max_corrections: int = 200                    # give up (unconfirmed) after this many
    # particles of the drill that keeps the strategy's code warm before a slip (identifier/drill.py);
    # 0: no drill.  A small copy suffices: warmth needs the code paths, not the cloud's size
    drill_particles: int = 64
    options: dict = field(default_factory=dict)   # strategy-specific tuning, by strategy name
    # the open-loop torque excitation while identifying ([identifier.excitation], identifier/excitation.py);
    # empty: none
    excitation: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.window_samples < 2 * ((len(self.initial_guess) - 1) // 2) + 2:
            raise ValueError("window_samples must exceed 2n + 1 (the SE of eq. 29 divides by L - 2n - 1)")
        if self.drill_particles != 0 and self.drill_particles < 2:
            raise ValueError(f"drill_particles must be 0 (no drill) or at least 2, got {self.drill_particles}")
        from .excitation import Excitation
        Excitation.from_dict(self.excitation)          # a bad table fails here, naming its field
