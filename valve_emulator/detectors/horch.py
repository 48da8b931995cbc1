r"""Horch's cross-correlation test for stiction in self-regulating loops.

A. Horch, "A simple method for detection of stiction in control valves", Control Engineering Practice 7 (1999)
1221–1231. In an oscillating self-regulating loop the cross-correlation between the controller output ``u``
and the process output ``y``

.. math::  r_{uy}(\tau) = \frac{\sum_k (u_k - \bar u)(y_{k+\tau} - \bar y)}{N\,\sigma_u \sigma_y}

is an **odd** function of the lag when a sticky valve causes the oscillation (``u`` ramps while ``y`` is nearly
square, a phase shift near 90°) and an **even** one when the oscillation comes from an external disturbance or
aggressive tuning (``u`` and ``y`` nearly in or out of phase). The test does not apply to integrating loops
(levels), for which Horch proposed a different test; this module answers "not applicable" there.

Decision rule as implemented
----------------------------
Horch (1999) states the criterion qualitatively. Here the lag-0 position is measured between the zero
crossings of :math:`r_{uy}` nearest to it, :math:`\tau_l \le 0 \le \tau_r`:

.. math::  \Delta = \frac{|\tau_r + \tau_l|}{\tau_r - \tau_l} \in [0, 1],

0 when lag 0 sits midway (an extremum: even), 1 when it sits on a crossing (odd). For a sinusoidal oscillation
:math:`\Delta = \varphi/90°`, with φ the phase between ``u`` and ``y`` folded into [0°, 90°]. The bands, chosen
once and the same for every loop: **Δ ≥ 2/3 stiction** (φ ≥ 60°), **Δ ≤ 1/3 no stiction** (φ ≤ 30°), between
undetermined. (Equal thirds are this project's formalisation of "odd"/"even", not numbers printed in the
1999 paper.) ``y`` is
``pv − sp`` when a set point is given, else ``pv``; the loop must first oscillate regularly
(:func:`~valve_emulator.detectors.base.oscillation` on ``y``).

Known behaviour: an external disturbance much slower than the loop's integral action is tracked by the
controller, which puts OP about 90° from the error, so such a loop reads "odd" and is called stiction (seen
here for a sine disturbance of period 300 s on the proof cases' concentration loop); this is a property of the
method, not corrected here.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.detectors.base import (
    MIN_SAMPLES,
    NO_STICTION,
    NOT_APPLICABLE,
    STICTION,
    UNDETERMINED,
    DetectorResult,
    oscillation,
    prepare,
    zero_crossings,
)

__all__ = ["horch", "ODD_THRESHOLD", "EVEN_THRESHOLD"]

ODD_THRESHOLD: Final = 2.0 / 3.0
EVEN_THRESHOLD: Final = 1.0 / 3.0
NAME: Final = "horch"


def _cross_correlation(u: np.ndarray, y: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    """Lags ``-max_lag..max_lag`` and :math:`r_{uy}` (positive lag: ``y`` after ``u``)."""
    u, y = u - u.mean(), y - y.mean()
    n = u.size
    full = np.fft.irfft(np.conj(np.fft.rfft(u, 2 * n)) * np.fft.rfft(y, 2 * n), 2 * n)
    r = np.concatenate((full[-max_lag:], full[: max_lag + 1])) / (n * u.std() * y.std())
    return np.arange(-max_lag, max_lag + 1), r


def horch(op: ArrayLike, pv: ArrayLike, *, dt: float, sp: ArrayLike | None = None,
          integrating: bool = False) -> DetectorResult:
    """Horch's (1999) cross-correlation test; see the module docstring for the rule and thresholds.

    Parameters
    ----------
    op, pv : controller output (%) and process value, equal length, finite.
    dt : sample time, s.
    sp : set point (optional; used as ``y = pv − sp`` when finite everywhere).
    integrating : the process integrates (level loops): the test does not apply.

    Returns
    -------
    DetectorResult
        ``indices``: ``delta`` (Δ), ``tau_left_s``, ``tau_right_s`` (s), ``period_s``, ``regularity``.
    """
    u, pv, s = prepare(op, pv, sp, dt)
    if integrating:
        return DetectorResult(NAME, NOT_APPLICABLE, {}, "integrating process: Horch's test is for "
                              "self-regulating loops")
    if u.size < MIN_SAMPLES:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{u.size} samples, at least {MIN_SAMPLES} needed")
    y = pv if s is None else pv - s
    if np.ptp(u) == 0 or np.ptp(y) == 0:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{'OP' if np.ptp(u) == 0 else 'PV'} is constant")
    osc = oscillation(y)
    base = {"period_s": osc.period * dt, "regularity": osc.regularity}
    if not osc.regular:
        return DetectorResult(NAME, UNDETERMINED, base, f"no regular oscillation (regularity "
                              f"{osc.regularity:.2f} <= 1)")
    lags, r = _cross_correlation(u, y, u.size // 2)
    mid = lags.size // 2
    right = zero_crossings(r[mid:])
    left = zero_crossings(r[mid::-1])
    if right.size == 0 or left.size == 0:
        return DetectorResult(NAME, UNDETERMINED, base, "the cross-correlation has no zero crossing on one "
                              "side of lag 0")
    tau_r, tau_l = float(right[0]), -float(left[0])
    delta = abs(tau_r + tau_l) / (tau_r - tau_l) if tau_r > tau_l else 1.0
    idx = {"delta": delta, "tau_left_s": tau_l * dt, "tau_right_s": tau_r * dt, **base}
    if delta >= ODD_THRESHOLD:
        return DetectorResult(NAME, STICTION, idx, f"cross-correlation odd: delta {delta:.2f} >= 2/3")
    if delta <= EVEN_THRESHOLD:
        return DetectorResult(NAME, NO_STICTION, idx, f"cross-correlation even: delta {delta:.2f} <= 1/3")
    return DetectorResult(NAME, UNDETERMINED, idx, f"cross-correlation neither odd nor even: 1/3 < delta "
                          f"{delta:.2f} < 2/3")
