"""An example suite: what a TCU must do on FFCC-a, judged over 1-second in-process lockstep runs.

    pytest -p hil.pytest_plugin scenarios/suites --hil-bus inprocess --junitxml report.xml

(``-p hil.pytest_plugin`` only where railway-hil is not installed: installed, the plugin loads itself.)
The built-in TCU passes every check; ``--hil-tcu external --hil-tcu-cmd "..."`` puts yours in its place.
"""
from pathlib import Path

from hil.checks import cycle_time, in_range, limit, require, responds, settles

FFCC_A = Path(__file__).resolve().parent.parent / "ffcc_a.toml"
ONE_SECOND = {"run.duration_s": 1.0}


def test_the_observer_holds_the_demanded_adhesion_before_the_fault(hil_run):
    run = hil_run(FFCC_A, set=ONE_SECOND)
    require(run,
            settles("TcuStatus.MuHat", band=(0.14, 0.18), within_s=0.05, hold_s=0.4, valid="TcuStatus.ObserverValid",
                    req="OBS-1"),
            cycle_time("TcuStatus", nominal_s=0.001, tolerance_s=0.0002, req="BUS-1"))


def test_the_slip_is_answered_and_the_curve_identified(hil_run):
    run = hil_run(FFCC_A, set=ONE_SECOND)
    require(run,
            responds("fault", "TcuStatus.Stage >= 1", within_s=0.05, req="DET-1"),
            in_range("TcuStatus.MuHat", 0.0, 0.35, during=("fault", 0.0, 0.2), valid="TcuStatus.ObserverValid",
                     req="OBS-2"),
            limit("t_identified_s", hi=0.7, req="ID-1"),
            limit("peak_mu_err_percent", hi=5.0, req="ID-2"))
