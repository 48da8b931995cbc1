"""Intervals from a cost surface: the effective sample size of a coloured residual, a region cut by its grid, the
grid's step at the interval's ends, and the delete-a-block jackknife that widens an interval where blocks of the
record disagree."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from valve_emulator.diagnosis.fit.uncertainty import (
    block_windows,
    effective_fraction,
    intervals,
    jackknifed,
    left_out,
    optimum,
    plausible,
    touches_edge,
)


def _ar1(rho: float, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w = rng.normal(size=n)
    e = np.zeros(n)
    for k in range(1, n):
        e[k] = rho * e[k - 1] + w[k]
    return e


@pytest.mark.parametrize("rho", [0.5, 0.9])
def test_an_ar1_residual_counts_as_its_bartlett_fraction_of_independent_samples(rho):
    assert effective_fraction(_ar1(rho, 40000)) == pytest.approx((1 - rho) / (1 + rho), rel=0.2)


def test_white_noise_counts_every_sample_and_a_random_walk_almost_none():
    rng = np.random.default_rng(1)
    w = rng.normal(size=5000)
    assert effective_fraction(w) > 0.9
    assert effective_fraction(np.cumsum(w)) < 0.01
    assert effective_fraction(np.zeros(50)) == 1.0


def test_a_slowly_wandering_error_is_counted_beyond_its_lag_one_correlation():
    # A sum of an AR(1) with a short memory and one with a long memory: the lag-1 correlation sees mostly the
    # short one, the integrated autocorrelation time both.
    e = _ar1(0.3, 40000, seed=2) + 0.5 * _ar1(0.99, 40000, seed=3)
    rho1 = float(np.corrcoef(e[1:], e[:-1])[0, 1])
    assert effective_fraction(e) < 0.5 * (1 - rho1) / (1 + rho1)


def _quadratic_surface(width: float, n: float, points: int = 20001):
    x = np.linspace(-1.0, 1.0, points)
    sse = 1.0 + (x / width) ** 2   # N ln(SSE/SSE_min) ≈ N (x/width)² near 0
    return x[:, None], sse


def test_fewer_effective_samples_give_a_wider_interval():
    params, sse = _quadratic_surface(0.1, 100)
    narrow = intervals(params, sse, 1000.0, ("x",), 1)["x"]
    wide = intervals(params, sse, 100.0, ("x",), 1)["x"]
    assert wide[0] < narrow[0] < 0.0 < narrow[1] < wide[1]
    assert (wide[1] - wide[0]) == pytest.approx(np.sqrt(10.0) * (narrow[1] - narrow[0]), rel=0.1)


def test_a_region_that_reaches_the_end_of_its_grid_is_said_to_touch_it():
    params, sse = _quadratic_surface(0.1, 100)
    assert touches_edge(params, sse, 1000.0, 1, 0) == (False, False)
    assert touches_edge(params, sse, 0.5, 1, 0) == (True, True)
    shifted = 1.0 + ((params[:, 0] - 0.99) / 0.1) ** 2
    assert touches_edge(params, shifted, 100.0, 1, 0) == (False, True)


def test_an_interval_ends_where_the_cost_crosses_its_bound_between_two_grid_values():
    # On a grid of step 0.1 the region of SSE = 1 + x² (N = 100) holds -0.1..0.1; the exact crossing of
    # N ln SSE = 3.84 is at |x| = 0.198. The interpolated end is there, not half a step past the last value inside
    # (0.15): a truth at 0.19 is in the interval.
    params, sse = _quadratic_surface(1.0, 100, points=21)
    lo, hi = intervals(params, sse, 100.0, ("x",), 1)["x"]
    exact = np.sqrt(np.expm1(chi2.ppf(0.95, 1) / 100))
    assert lo == pytest.approx(-exact, abs=0.005) and hi == pytest.approx(exact, abs=0.005)


def test_an_interval_ends_at_least_half_a_grid_step_beyond_the_last_value_inside():
    # A cost that jumps just past 0.1: the crossing interpolates to barely beyond 0.1, but the grid cannot say
    # where between 0.1 and 0.2 the jump is, so the interval keeps half a step.
    x = np.round(np.arange(-1.0, 1.0001, 0.1), 10)
    sse = np.where(np.abs(x) <= 0.1 + 1e-9, 1.0, 1e6)
    lo, hi = intervals(x[:, None], sse, 100.0, ("x",), 1)["x"]
    assert lo == pytest.approx(-0.15) and hi == pytest.approx(0.15)


def test_blocks_cut_the_window_into_consecutive_parts_of_equal_length():
    windows = block_windows((100, 900), 8)
    assert windows[0][0] == 100 and windows[-1][1] == 900
    assert all(a[1] == b[0] for a, b in zip(windows, windows[1:]))
    assert {b - a for a, b in windows} == {100}


def _block_surfaces(optima: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Rows x = 0..10 (step 0.1) and each block's SSE, a parabola about that block's own optimum."""
    x = np.round(np.arange(0.0, 10.0001, 0.1), 10)[:, None]
    return x, np.array([1.0 + (x[:, 0] - m) ** 2 for m in optima])


def test_the_optimum_of_a_surface_lies_between_its_grid_values():
    x = np.round(np.arange(0.0, 10.0001, 0.1), 10)
    assert optimum(x[:, None], (x - 5.03) ** 2, 0) == pytest.approx(5.03)
    # on two columns, along each one the least over the other
    grid = np.array([(a, b) for a in x[::10] for b in x[::10]])
    sse = (grid[:, 0] - 3.3) ** 2 + 2.0 * (grid[:, 1] - 6.6) ** 2
    assert optimum(grid, sse, 0) == pytest.approx(3.3) and optimum(grid, sse, 1) == pytest.approx(6.6)
    # at the end of the grid it is the end
    assert optimum(x[:, None], (x - 12.0) ** 2, 0) == 10.0


def test_each_left_out_estimate_is_the_optimum_of_the_other_blocks():
    rows, sse = _block_surfaces([4.0, 6.0, 5.0, 5.0])
    # the mean of the other three optima
    assert left_out(rows, sse, (0,))[:, 0] == pytest.approx([16 / 3, 14 / 3, 5.0, 5.0])


def test_the_rows_the_whole_record_allows_are_those_inside_a_wide_region():
    x = np.linspace(-1.0, 1.0, 201)
    inside = plausible(1.0 + x ** 2, 100.0, 1)   # 100 ln(1 + x²) ≤ 10.83 (χ²₁ at 99.9 %)
    assert np.abs(x[inside]).max() == pytest.approx(np.sqrt(np.expm1(10.83 / 100)), abs=0.01)


def test_blocks_that_agree_leave_the_interval_as_it_was():
    rows, sse = _block_surfaces([5.0] * 8)
    ivs = {"x": (4.6, 5.4)}
    assert jackknifed(ivs, {"x": 5.0}, left_out(rows, sse, (0,)), ("x",)) == ivs


def test_blocks_that_disagree_widen_the_interval_by_the_jackknife_standard_error():
    rows, sse = _block_surfaces([4.0, 6.0] * 4)
    left = left_out(rows, sse, (0,))
    # left-out means 5 ± 1/7: se = sqrt(7/8 · 8 · (1/7)²) = 0.378; t₇ = 2.3646
    lo, hi = jackknifed({"x": (4.9, 5.1)}, {"x": 5.0}, left, ("x",))["x"]
    se = np.sqrt(7) / 7
    assert lo == pytest.approx(5.0 - 2.3646 * se, rel=1e-3) and hi == pytest.approx(5.0 + 2.3646 * se, rel=1e-3)
    # a name without an interval gets none, a single block changes nothing
    assert "y" not in jackknifed({"x": (4.9, 5.1)}, {"x": 5.0, "y": 1.0}, np.hstack([left, left]), ("x", "y"))
    assert jackknifed({"x": (4.9, 5.1)}, {"x": 5.0}, left[:1], ("x",)) == {"x": (4.9, 5.1)}
