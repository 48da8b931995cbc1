"""Intervals from a cost surface: the effective sample size of a coloured residual and a region cut by its grid."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.diagnosis.fit.uncertainty import effective_fraction, intervals, touches_edge


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


def _quadratic_surface(width: float, n: float):
    x = np.linspace(-1.0, 1.0, 201)
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
