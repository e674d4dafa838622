"""railway-hil: a hardware-in-the-loop testbench for railway traction.

The public API.  Each name is imported on first use (module ``__getattr__``), so that a process that
needs one piece -- a TCU child importing ``hil.tcu_node``, a python-can program opening the ``localbus``
interface -- pays for none of the others::

    import hil

    scenario = hil.load_scenario("scenarios/ffcc_a.toml", {"run.seed": 2})
    summary = hil.run(scenario)                     # one HIL run; its summary is `hil run --json`
    log = hil.read_log(summary["mcap"])             # the run's log back, topic by topic
    again = hil.replay_log(summary["mcap"])         # re-identified offline; again["matches_log"]
    report, diagnosis = hil.diagnose(hil.read_real_log(path), scenario)   # the sim-to-real gap

Every error these raise is a ``hil.HilError`` with a one-line message and the exit code the command
line would end with (``hil.errors``).
"""
from __future__ import annotations

import importlib

#: public name -> the module that defines it
_API = {
    "run": "hil.exchange",
    "load_scenario": "hil.config",
    "parse_scenario": "hil.config",
    "Scenario": "hil.config",
    "read_log": "hil.log.read",
    "replay_log": "hil.replay",
    "read_real_log": "hil.gap",
    "diagnose": "hil.gap",
    "HilError": "hil.errors",
    "ConfigError": "hil.errors",
    "BusError": "hil.errors",
    "LogError": "hil.errors",
    "LogWriteError": "hil.errors",
    "PlantError": "hil.errors",
    "ClusterError": "hil.errors",
    "PeerSilent": "hil.errors",
    "NoProgress": "hil.errors",
    "TcuDidNotStart": "hil.errors",
    "ScenarioMismatch": "hil.errors",
    "PlantFault": "hil.errors",
    "DeadlinesMissed": "hil.errors",
    "BenchError": "hil.errors",
}

__all__ = sorted(_API)


def __getattr__(name: str):
    try:
        module = _API[name]
    except KeyError:
        raise AttributeError(f"module 'hil' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value          # imported once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
