"""A grid scored at a held gain is fitted at that gain (:func:`~valve_emulator.diagnosis.fit.linear.
input_grid_sse` of a structure with ``gain``): the nominal model's gain test refines the findings around the held
gain, and a grid that fitted the gain freely chose the rows that suit the other gain (docs/diagnosis.md, *Physics
that starts part-way*). The compiled pass adds what holding the taps' sum costs to the free fit's SSE; the known
truth here is a plant written from its difference equation, and the reference each grid entry must equal is
:func:`~valve_emulator.diagnosis.fit.linear.fit_one`'s residual at the held gain (its regressors built and
solved by least squares, no shared code with the kernel's normal equations)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.signal import lfilter

from valve_emulator.diagnosis.fit.linear import LinearStructure, fit_one, highpass, input_grid_sse

T, DT, TAU, GAIN, DELAY = 800, 1.0, 6.0, 0.7, 3


def _plant(u: np.ndarray, integrating: bool) -> np.ndarray:
    """The known truth: a first-order lag (gain GAIN, τ TAU, zero-order hold) behind DELAY samples, written
    from its difference equation; integrating, its output summed (gain per second)."""
    a = np.exp(-DT / TAU)
    x = np.concatenate([np.full(DELAY + 1, u[0]), u[:-DELAY - 1]])
    y = lfilter([GAIN * (1.0 - a)], [1.0, -a], x - u[0])
    return np.cumsum(y) * DT if integrating else y


@pytest.mark.parametrize(("integrating", "prefilter", "frac"), [(False, None, 0.0), (True, None, 0.0),
                                                               (True, 0.9, 0.0), (False, 0.9, 0.3)])
def test_at_the_true_gain_the_fit_is_exact_and_at_another_it_is_fit_ones(integrating, prefilter, frac):
    rng = np.random.default_rng(3)
    u = np.repeat(rng.normal(size=(T // 20, 4)), 20, axis=0).cumsum(axis=0) * 0.2
    y = _plant(u[:, 0], integrating)
    y_cost = y if prefilter is None else highpass(y, prefilter)
    window, delays = (40, T), np.array([DELAY - 1, DELAY, DELAY + 1])
    true = LinearStructure(taus=(TAU,), integrating=integrating, gain=GAIN)
    wrong = LinearStructure(taus=(TAU,), integrating=integrating, gain=2.0 * GAIN)
    at_true = input_grid_sse(u, y_cost, window, delays, true, DT, prefilter=prefilter)
    at_wrong = input_grid_sse(u, y_cost, window, delays, wrong, DT, prefilter=prefilter, frac=frac)
    scale = float(np.sum((y_cost[window[0]:] - y_cost[window[0]:].mean()) ** 2))
    # the plant's own column, dead time and gain: exact but for the prefilter's start (1.5e-6 of the scale on
    # the integrator, as the free fit's own)
    assert at_true[0, 1] < 1e-5 * scale
    assert at_wrong[0, 1] > 1e-3 * scale                 # held at twice the gain, the same column fits badly
    # each entry is fit_one's SSE of that column alone at the held gain, dead time by dead time; an integrator's
    # unfiltered ramps cost the normal equations digits (the free pass is 6e-6 off fit_one there, this 2.5e-5)
    rel = 1e-4 if integrating and prefilter is None else 1e-6
    for j in range(u.shape[1]):
        for k, d in enumerate(delays):
            one = fit_one(u[:, j], y, window, replace(wrong, delay=float(d) + frac), DT, prefilter=prefilter)
            assert at_wrong[j, k] == pytest.approx(one.sse, rel=rel, abs=1e-9 * scale)
    # fitted freely (no held gain) the same grid finds the plant exact at any gain: what the grid did before
    free = input_grid_sse(u, y_cost, window, delays, replace(wrong, gain=None), DT, prefilter=prefilter)
    assert free[0, 1] < 1e-5 * scale


def test_a_column_that_never_moves_is_scored_at_its_offset_whatever_the_gain():
    u = np.ones((T, 2))
    u[:, 1] = np.sin(np.arange(T) / 15.0)
    y = _plant(u[:, 1], False)
    sse = input_grid_sse(u, y, (40, T), np.array([DELAY]), LinearStructure(taus=(TAU,), gain=GAIN), DT)
    assert np.all(np.isfinite(sse))
    assert sse[0, 0] == pytest.approx(float(np.sum((y[40:] - y[40:].mean()) ** 2)), rel=1e-6)
    assert sse[1, 0] < 1e-9 * sse[0, 0]
