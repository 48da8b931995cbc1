"""The numbers a fit is judged by, and where the held-out part starts."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.diagnosis.fit.cost import bic, log_sse, relative_cost
from valve_emulator.diagnosis.fit.data import HELD_OUT, fold_windows, held_out_start


def test_a_parameter_more_costs_ln_n_and_halving_the_sse_gains_n_ln_2():
    n = 500
    assert bic(2.0, n, 4) - bic(2.0, n, 3) == pytest.approx(np.log(n))
    assert bic(2.0, n, 3) - bic(1.0, n, 3) == pytest.approx(n * np.log(2.0))
    assert log_sse(2.0, n) - log_sse(1.0, n) == pytest.approx(n * np.log(2.0))


def test_a_perfect_fit_has_a_finite_cost():
    assert np.isfinite(log_sse(0.0, 100)) and np.isfinite(bic(0.0, 100, 2))
    assert np.all(np.isfinite(relative_cost(np.array([0.0, 1.0]), 100)))


def test_the_relative_cost_is_zero_at_the_surfaces_best_point_and_on_the_chi_square_scale_elsewhere():
    sse = np.array([4.0, 2.0, 2.0 * np.exp(3.84 / 1000)])
    cost = relative_cost(sse, 1000)
    assert cost[1] == 0.0 and cost[2] == pytest.approx(3.84) and cost[0] == pytest.approx(1000 * np.log(2.0))


def test_the_held_out_part_is_the_last_share_of_the_record_for_the_split_and_the_folds():
    assert held_out_start(1000) == 1000 - round(HELD_OUT * 1000)
    (fit_a, test_a), _ = fold_windows(1000, 50)
    assert fit_a == (50, held_out_start(1000)) and test_a == (held_out_start(1000), 1000)
