"""The diagnosis computes a few of scipy's results itself (an IIR filter, a state-space realisation, a detrend, the
chi-square and t quantiles) so that it need not import scipy.signal and scipy.stats: each gives scipy's numbers
bit for bit, and importing the diagnosis leaves those two subpackages unloaded."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy import signal, stats

from valve_emulator.detectors.base import detrend
from valve_emulator.diagnosis.fit.continuous import _controllable_form, _numerator
from valve_emulator.diagnosis.fit.linear import highpass, iir_filter
from valve_emulator.diagnosis.fit.uncertainty import chi2_quantile, student_t_quantile


def _same_bits(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("seed", range(40))
def test_iir_filter_is_lfilter_bit_for_bit(seed):
    """Any order, numerator shorter or longer than the denominator, a[0] ≠ 1, one column or several, with and
    without an initial state."""
    rng = np.random.default_rng(seed)
    order = int(rng.integers(0, 4))
    a = np.r_[rng.choice([1.0, 1.7]), 0.3 * rng.normal(size=order)]
    b = rng.normal(size=int(rng.integers(1, order + 3)))
    x = rng.normal(size=(int(rng.integers(1, 200)), int(rng.integers(1, 4))))
    x = x[:, 0] if seed % 3 == 0 else x
    m = max(a.size, b.size)
    if m > 1 and seed % 2:
        zi = rng.normal(size=(m - 1,) + x.shape[1:])
        assert _same_bits(iir_filter(b, a, x, zi), signal.lfilter(b, a, x, axis=0, zi=zi)[0])
    else:
        assert _same_bits(iir_filter(b, a, x), signal.lfilter(b, a, x, axis=0))


def test_highpass_is_the_first_difference_filter_started_at_rest():
    x = np.cumsum(np.random.default_rng(1).normal(size=(500, 2)), axis=0)
    assert _same_bits(highpass(x, 0.95), signal.lfilter([1.0, -1.0], [1.0, -0.95], x - x[0], axis=0))


@pytest.mark.parametrize("seed", range(40))
def test_controllable_form_and_numerator_are_tf2ss_and_ss2tf_bit_for_bit(seed):
    """Including numerators whose leading coefficient is zero, rounding noise (trimmed) or significant."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 5))
    den = np.r_[rng.choice([1.0, 2.5]), rng.normal(size=n)]
    num = np.r_[rng.choice([0.0, 1e-16, -3e-15, 1e-3]), rng.normal(size=n)]
    if seed % 4 == 0:
        num[1] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", signal.BadCoefficients)
        A, B, C, _ = signal.tf2ss(num, den)
    mine = _controllable_form(num, den)
    assert all(_same_bits(x, y) for x, y in zip(mine, (A, B, C)))
    L = rng.normal(size=(n + 1, n + 1))
    expected, _ = signal.ss2tf(L[:n, :n], L[:n, n:], C, np.zeros((1, 1)))
    assert _same_bits(_numerator(L[:n, :n], L[:n, n:], C), expected[0])


@pytest.mark.parametrize("n", [8, 9, 100, 1001])
def test_detrend_is_scipy_linear_detrend_bit_for_bit(n):
    t = np.arange(n)
    x = 0.3 * t + np.sin(t / 7.0) + np.random.default_rng(n).normal(size=n)
    assert _same_bits(detrend(x), signal.detrend(x))


@pytest.mark.parametrize("p", [0.5, 0.9, 0.95, 0.975, 0.999])
@pytest.mark.parametrize("dof", [1, 2, 3, 4, 7, 19, 100])
def test_quantiles_are_scipy_stats_bit_for_bit(p, dof):
    assert chi2_quantile(p, dof) == float(stats.chi2.ppf(p, dof))
    assert student_t_quantile(p, dof) == float(stats.t.ppf(p, dof))


def test_importing_the_diagnosis_loads_neither_scipy_signal_nor_scipy_stats():
    """Together ~0.6 s of a first diagnosis' start; the comparison detectors still load them when used."""
    code = ("import sys, valve_emulator as ve, valve_emulator.diagnosis.explain.pipeline, "
            "valve_emulator.diagnosis.report.diagnosis, valve_emulator.diagnosis.api, valve_emulator.config\n"
            "print(sorted(m for m in sys.modules if m.startswith(('scipy.signal', 'scipy.stats'))))\n"
            "from valve_emulator.detectors import DETECTORS\n"
            "print('scipy.signal' in sys.modules, list(DETECTORS))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ["[]", "True ['horch', 'he', 'bicoherence']"]
