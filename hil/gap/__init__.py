"""Sim-to-real gap diagnosis (``hil gap``): where the gap lies, which unmodelled effect explains it,
how far it shrinks with that effect added -- judged on held-out data, never on the reality truth.

The diagnosis reads logs only through ``data.read_real_log``, which drops the truth.
"""
from .data import RealData, read_real_log
from .diagnose import NONE, Diagnosis, DiagnosisResult, diagnose

__all__ = ["RealData", "read_real_log", "NONE", "Diagnosis", "DiagnosisResult", "diagnose"]
