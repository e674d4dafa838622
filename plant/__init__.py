"""Wheelset-rail physics: friction curves, the CasADi plant, sensors, fault stages. No CAN here."""
from .friction import FrictionCurve, PolachCurve
from .model import (Plant, PlantConfig, PlantState, WheelsetPlant, creep_speed_kmh, equilibrium,
                    train_speed_before_fault)
from .params import KMH_PER_MS, WheelsetParams
from .sensors import SensorConfig, SensorModel
from .stages import EARLY, NORMAL, SERIOUS, StageTracker

__all__ = ["FrictionCurve", "PolachCurve", "Plant", "PlantConfig", "PlantState", "WheelsetPlant", "creep_speed_kmh",
           "equilibrium", "train_speed_before_fault", "KMH_PER_MS", "WheelsetParams", "SensorConfig", "SensorModel",
           "StageTracker", "NORMAL", "EARLY", "SERIOUS"]
