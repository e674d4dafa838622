"""The TCU: estimation and control (observer, curve model, strategies, control laws, evaluation, metrics).
No processes, no CAN."""
from .messages import (IdentificationEvent, ObserverSample, SensorReading, TcuOutput, TcuStatus,
                       TorqueCommand)
from .settings import IdentifierSettings, VehicleModel
from .strategies import DEFAULT_STRATEGY, STRATEGIES, make_strategy
from .tcu import TractionIdentifier

__all__ = ["IdentificationEvent", "ObserverSample", "SensorReading", "TcuOutput", "TcuStatus", "TorqueCommand",
           "IdentifierSettings", "VehicleModel", "DEFAULT_STRATEGY", "STRATEGIES", "make_strategy", "TractionIdentifier"]
