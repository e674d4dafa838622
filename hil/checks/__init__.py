"""Test verdicts over a recorded run: checks (``in_range``, ``limit``, ``responds``, ``cycle_time``,
``settles``), ``require`` to judge them together, and the ``Run`` they judge (a log read back).

    from hil.checks import require, in_range, limit

    require("logs/ffcc_a-gp-1.mcap",
            in_range("TcuStatus.MuHat", 0.0, 0.35, during=("fault", 0.0, 0.3), valid="TcuStatus.ObserverValid"),
            limit("t_identified_s", hi=0.8, req="REQ-ID-1"))

The checks are pure functions over the run (numpy over the decoded log); ``hil check`` judges a log
against a checks file (``hil.checks.spec``), the pytest plugin (``hil.pytest_plugin``) inside a test.
"""
from .kinds import (Check, CheckFailed, Result, cycle_time, in_range, limit, require, responds,  # noqa: F401
                    settles, torque_sign)
from .run import Run, Series  # noqa: F401

__all__ = ["Check", "CheckFailed", "Result", "Run", "Series", "cycle_time", "in_range", "limit", "require",
           "responds", "settles", "torque_sign"]
