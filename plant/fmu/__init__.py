"""The plant as an FMU: FMI 2.0 (and 3.0) Co-Simulation export of the CasADi wheelset model (see export.py)."""
from .export import (GENERATION_TOOL, INPUT, MODEL_IDENTIFIER, OUTPUTS, FmuExportError, export_fmu,
                     model_param_names, parameter_values)

__all__ = ["GENERATION_TOOL", "INPUT", "MODEL_IDENTIFIER", "OUTPUTS", "FmuExportError", "export_fmu",
           "model_param_names", "parameter_values"]
