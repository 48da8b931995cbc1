"""Describing function of the stiction model against the first harmonic of simulated MV."""

from __future__ import annotations

import numpy as np
import pytest

from valve_emulator.physics.describing_function import describing_function, negative_reciprocal
from valve_emulator.stiction import simulate

SAMPLES_PER_PERIOD = 20_000
OFFSET = 50.0  # centre of travel, so that OP never saturates at 0/100


def simulated_first_harmonic(A: float, S: float, J: float) -> complex:
    """First Fourier coefficient ``b1 + j a1`` of MV for OP = 50 + A sin(theta), over whole periods.

    OP starts at its peak (a cosine) with the valve at rest having moved up, which is the state the valve
    is in at that phase of the steady oscillation; otherwise an overshoot valve (J > S) started mid-stroke
    would need J of further travel and, for A < J, never move. The first period is dropped anyway.
    """
    n = SAMPLES_PER_PERIOD
    theta = 2 * np.pi * np.arange(3 * n) / n
    op = OFFSET + A * np.cos(theta)
    mv = simulate(op, S=S, J=J, model="kano", direction=1) - OFFSET
    w = slice(n, 3 * n)  # two whole periods after the first
    # With OP = A cos(theta) = A sin(theta + pi/2), the in-phase and quadrature parts are cos and -sin.
    in_phase = 2 * np.mean(mv[w] * np.cos(theta[w]))
    quadrature = -2 * np.mean(mv[w] * np.sin(theta[w]))
    return complex(in_phase, quadrature)


CASES = [
    # (A, S, J): deadband, undershoot, no offset, overshoot; A above S, and S/2 < A < S (phi < 0)
    (5.0, 3.0, 0.0),
    (2.0, 3.0, 0.0),
    (1.6, 3.0, 0.0),
    (5.0, 3.0, 1.5),
    (2.0, 3.0, 1.5),
    (1.6, 3.0, 1.5),
    (4.0, 3.0, 3.0),
    (2.0, 3.0, 3.0),
    (2.5, 3.0, 4.5),
    (10.0, 5.0, 2.0),
    (3.0, 5.0, 2.0),
    (4.0, 5.0, 7.0),
    (30.0, 5.0, 7.0),
]


@pytest.mark.parametrize(("A", "S", "J"), CASES)
def test_matches_first_harmonic_of_simulated_mv(A, S, J):
    expected = describing_function(A, S, J) * A
    got = simulated_first_harmonic(A, S, J)
    assert abs(got - expected) / abs(expected) < 1e-3


def test_vectorised_over_amplitude_and_zero_below_half_S():
    A = np.array([[0.0, 1.0, 1.5], [1.5000001, 3.0, 100.0]])
    N = describing_function(A, 3.0, 1.5)
    assert N.shape == A.shape and N.dtype == complex
    assert np.all(N[0] == 0)  # A <= S/2: the valve never moves
    assert np.all(N[1] != 0)
    for a, n in zip(A.ravel(), N.ravel()):
        assert n == describing_function(a, 3.0, 1.5)


def test_known_limits():
    S, J = 4.0, 1.0
    # Just above S/2 the valve only slips by J at each reversal: a square wave of height J, phase -90 deg.
    A = S / 2 * (1 + 1e-12)
    assert describing_function(A, S, J) == pytest.approx(-2j * J / (np.pi * A), rel=1e-5)
    # Backlash (J = 0) is continuous at S/2 and every stiction N tends to 1 for large amplitude.
    assert abs(describing_function(A, S, 0.0)) < 1e-5
    assert describing_function(1e7, S, J) == pytest.approx(1.0, abs=1e-6)
    # No friction at all is a unit gain.
    assert describing_function(2.0, 0.0, 0.0) == pytest.approx(1.0)


def test_negative_reciprocal_is_nan_where_valve_never_moves():
    loc = negative_reciprocal([1.0, 4.0], 3.0, 1.5)
    assert np.isnan(loc[0].real) and np.isnan(loc[0].imag)
    assert loc[1] == pytest.approx(-1 / describing_function(4.0, 3.0, 1.5))


@pytest.mark.parametrize(("A", "S", "J", "name"), [
    (-1.0, 3.0, 1.0, "A"), (np.nan, 3.0, 1.0, "A"), (1.0, -3.0, 1.0, "S"), (1.0, 3.0, np.inf, "J"),
])
def test_rejects_bad_input(A, S, J, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        describing_function(A, S, J)
