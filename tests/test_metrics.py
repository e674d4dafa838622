"""Goodness-of-fit figures against the true curve (identifier/metrics.py)."""
import math

import numpy as np

from identifier.metrics import r2_vs_truth

FFCC_A = np.array([-0.005, 0.585, -0.580, -0.525, -1.100])


def curve(v, th):
    return th[0] + th[1] * np.exp(th[3] * v) + th[2] * np.exp(th[4] * v)


def test_r2_vs_truth_is_one_for_the_true_curve_and_falls_with_an_offset():
    assert r2_vs_truth(FFCC_A, FFCC_A, 2.5) == 1.0
    grid = np.linspace(0.0, 2.5, 200)
    truth = curve(grid, FFCC_A)
    ss_tot = np.sum((truth - truth.mean()) ** 2)
    for offset in (0.001, 0.003):
        shifted = FFCC_A + np.array([offset, 0, 0, 0, 0])
        assert math.isclose(r2_vs_truth(shifted, FFCC_A, 2.5), 1.0 - 200 * offset ** 2 / ss_tot, rel_tol=1e-9)
    assert r2_vs_truth(FFCC_A * np.array([1, 1.1, 1, 1, 1]), FFCC_A, 2.5) < r2_vs_truth(FFCC_A + 0.001 * np.eye(5)[0],
                                                                                            FFCC_A, 2.5)


def test_r2_vs_truth_of_an_overflowing_curve_is_nan_not_an_error():
    assert math.isnan(r2_vs_truth(np.array([0.0, 1.0, -1.0, 800.0, -1.0]), FFCC_A, 2.5))
