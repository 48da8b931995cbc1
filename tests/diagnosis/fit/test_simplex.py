"""The diagnosis' Nelder–Mead visits the points scipy's visits and stops where it stops, bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize

from valve_emulator.diagnosis.fit.simplex import nelder_mead


def _rosenbrock(x: np.ndarray) -> float:
    return float(np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2))


def _rough(x: np.ndarray) -> float:
    """A cost with flat steps (equal costs at different points: the ranking's ties) and a noisy floor."""
    return float(np.floor(4.0 * np.sum((x - 0.3) ** 2)) / 4.0 + 1e-3 * np.sin(37.0 * x).sum())


def _nan_outside(x: np.ndarray) -> float:
    """NaN outside the unit ball: NaN costs enter the ranking and the stopping test."""
    r = float(np.sum(x * x))
    return float("nan") if r > 1.0 else (r - 0.2) ** 2 + 0.1 * x[0]


def _simplex(x0: np.ndarray, step: float) -> np.ndarray:
    return np.vstack([x0] + [x0 + np.eye(x0.size)[i] * step for i in range(x0.size)])


def _scipy(cost, simplex, maxfev, xatol, fatol):
    points = []

    def traced(x):
        points.append(x.tobytes())
        return cost(x)

    res = minimize(traced, simplex[0], method="Nelder-Mead",
                   options={"initial_simplex": simplex, "maxfev": maxfev, "xatol": xatol, "fatol": fatol})
    return res, points


@pytest.mark.parametrize("cost", [_rosenbrock, _rough, _nan_outside])
@pytest.mark.parametrize("dim", [1, 2, 3, 5])
@pytest.mark.parametrize("maxfev, tol", [(200, 1e-3), (9, 1e-3), (400, 1e-9)])
def test_nelder_mead_visits_scipys_points_and_returns_its_minimum(cost, dim, maxfev, tol):
    simplex = _simplex(np.linspace(-0.4, 0.5, dim), 0.3)
    expected, scipy_points = _scipy(cost, simplex, maxfev, tol, tol)
    points = []

    def traced(x):
        points.append(x.tobytes())
        return cost(x)

    got = nelder_mead(traced, simplex, maxfev=maxfev, xatol=tol, fatol=tol)
    assert points == scipy_points
    assert got.x.tobytes() == np.asarray(expected.x, dtype=float).tobytes()
    assert (math.isnan(got.fun) and math.isnan(expected.fun)) or got.fun == expected.fun
    start = cost(simplex[0])
    assert (math.isnan(got.start) and math.isnan(start)) or got.start == start
