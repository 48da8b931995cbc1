r"""He et al.'s curve-fitting stiction index.

Q. P. He, J. Wang, M. Pottmann, S. J. Qin, "A curve fitting method for detecting valve stiction in oscillating
control loops", Ind. Eng. Chem. Res. 46 (2007) 4549–4560. A sticky valve in a self-regulating loop makes the
controller output a **triangular** wave (the integral of a nearly square error); in an integrating loop the
process output is the triangular one. A linear cause (disturbance, tuning) gives rounder, **sinusoidal**
shapes. Each half cycle of the signal is fitted with both shapes and

.. math::  SI = \frac{MSE_{sin}}{MSE_{sin} + MSE_{tri}} ;

as described by He et al., **SI ≥ 0.6 stiction, SI ≤ 0.4 no stiction**, between undetermined.

Fits as implemented
-------------------
The signal ``x`` (``op`` for a self-regulating process, ``pv`` for an integrating one), linearly detrended, is
cut into half cycles at its zero crossings, found on a copy smoothed by a centred moving average one eighth of
the oscillation period long (so noise does not add crossings); the partial first and last pieces are dropped.
On each half cycle of ``L`` samples, with the same number of free parameters for both shapes,

* sinusoid: :math:`a + b\sin\omega k + c\cos\omega k`, linear least squares in ``a, b, c`` for each ω on a grid
  of 17 values from ``0.6π/L`` to ``1.4π/L``, the best ω kept;
* triangle: :math:`a + b k + c\,\max(0, k - p)` (two straight lines meeting at the peak ``p``), least squares in
  ``a, b, c`` for each peak position ``p`` (between samples too: a grid of at most about 200 positions over the
  half cycle, then steps of 1/20 sample around the best), the best ``p`` kept.

``MSE`` is the mean squared residual over all fitted samples. The loop must oscillate regularly
(:func:`~valve_emulator.detectors.base.oscillation` on ``x``) with at least two whole half cycles.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage, signal

from valve_emulator.detectors.base import (
    MIN_SAMPLES,
    NO_STICTION,
    STICTION,
    UNDETERMINED,
    DetectorResult,
    oscillation,
    prepare,
)

__all__ = ["he_curve_fit", "STICTION_THRESHOLD", "NO_STICTION_THRESHOLD"]

STICTION_THRESHOLD: Final = 0.6
NO_STICTION_THRESHOLD: Final = 0.4
NAME: Final = "he"
_OMEGA_FACTORS: Final = np.linspace(0.6, 1.4, 17)
_MIN_HALF_CYCLE: Final = 4  # samples: fewer cannot tell a line from a curve
_MAX_PEAKS: Final = 200     # coarse peak grid of the triangle fit (memory: peaks x 3 x half-cycle length)


def _sse_sine(x: np.ndarray) -> float:
    k = np.arange(x.size, dtype=float)
    best = np.inf
    for f in _OMEGA_FACTORS:
        w = f * np.pi / x.size
        basis = np.column_stack((np.ones_like(k), np.sin(w * k), np.cos(w * k)))
        coef, *_ = np.linalg.lstsq(basis, x, rcond=None)
        best = min(best, float(np.sum((x - basis @ coef) ** 2)))
    return best


def _sse_triangle_at(x: np.ndarray, peaks: np.ndarray) -> tuple[float, float]:
    """Least squares for each peak position at once (3x3 normal equations); best SSE and its peak."""
    k = np.arange(x.size, dtype=float)
    basis = np.stack([np.broadcast_to(np.ones_like(k), (peaks.size, k.size)),
                      np.broadcast_to(k, (peaks.size, k.size)),
                      np.maximum(0.0, k[None, :] - peaks[:, None])], axis=1)      # (P, 3, L)
    gram = basis @ basis.transpose(0, 2, 1)
    coef = np.linalg.solve(gram, (basis @ x)[..., None])[..., 0]
    sse = np.sum((x[None, :] - np.einsum("pi,pil->pl", coef, basis)) ** 2, axis=1)
    best = int(np.argmin(sse))
    return float(sse[best]), float(peaks[best])


def _sse_triangle(x: np.ndarray) -> float:
    """Best two-line fit. The peak may fall between samples (a coarse half cycle has its corner anywhere), so
    peak positions are tried on a grid of at most ~200 points over the half cycle, then every 1/20 sample
    around the best one."""
    last = x.size - 1.0
    # Corners strictly inside the half cycle: at an end the two lines degenerate into one.
    coarse = np.linspace(0.0, last, int(min(_MAX_PEAKS, 20 * last)) + 1)[1:-1]
    sse, p = _sse_triangle_at(x, coarse)
    step = last / (coarse.size + 1)
    if step > 0.05:
        fine = np.arange(max(0.05, p - step), min(last - 0.05, p + step), 0.05)
        if fine.size:
            sse = min(sse, _sse_triangle_at(x, fine)[0])
    return sse


def _half_cycles(x: np.ndarray, period: float) -> list[tuple[int, int]]:
    """``(i0, i1)`` of the whole half cycles between sign changes of the smoothed signal."""
    width = max(1, int(round(period / 8)))
    smooth = ndimage.uniform_filter1d(x, width, mode="nearest")
    sign = np.sign(smooth)
    cross = np.flatnonzero(sign[:-1] * sign[1:] < 0) + 1
    return [(int(a), int(b)) for a, b in zip(cross[:-1], cross[1:]) if b - a >= _MIN_HALF_CYCLE]


def he_curve_fit(op: ArrayLike, pv: ArrayLike, *, dt: float, sp: ArrayLike | None = None,
                 integrating: bool = False) -> DetectorResult:
    """He et al.'s (2007) curve-fitting stiction index; see the module docstring.

    Parameters
    ----------
    op, pv : controller output (%) and process value, equal length, finite.
    dt : sample time, s.
    sp : set point (not used by this method; accepted for a uniform signature).
    integrating : fit ``pv`` (integrating process) instead of ``op``.

    Returns
    -------
    DetectorResult
        ``indices``: ``si``, ``mse_sin``, ``mse_tri``, ``half_cycles``, ``period_s``, ``regularity``.
    """
    op, pv, _ = prepare(op, pv, sp, dt)
    name = "PV" if integrating else "OP"
    x = pv if integrating else op
    if x.size < MIN_SAMPLES:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{x.size} samples, at least {MIN_SAMPLES} needed")
    if np.ptp(x) == 0:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{name} is constant")
    x = signal.detrend(x)
    osc = oscillation(x)
    base = {"period_s": osc.period * dt, "regularity": osc.regularity}
    if not osc.regular:
        return DetectorResult(NAME, UNDETERMINED, base, f"{name} has no regular oscillation (regularity "
                              f"{osc.regularity:.2f} <= 1)")
    pieces = _half_cycles(x, osc.period)
    if len(pieces) < 2:
        return DetectorResult(NAME, UNDETERMINED, base, f"{name} has {len(pieces)} whole half cycle(s), "
                              "at least 2 needed")
    n = sum(b - a for a, b in pieces)
    mse_sin = sum(_sse_sine(x[a:b]) for a, b in pieces) / n
    mse_tri = sum(_sse_triangle(x[a:b]) for a, b in pieces) / n
    total = mse_sin + mse_tri
    si = 0.5 if total == 0 else mse_sin / total
    idx = {"si": si, "mse_sin": mse_sin, "mse_tri": mse_tri, "half_cycles": len(pieces), **base}
    if si >= STICTION_THRESHOLD:
        return DetectorResult(NAME, STICTION, idx, f"{name} is triangular: SI {si:.2f} >= 0.6")
    if si <= NO_STICTION_THRESHOLD:
        return DetectorResult(NAME, NO_STICTION, idx, f"{name} is sinusoidal: SI {si:.2f} <= 0.4")
    return DetectorResult(NAME, UNDETERMINED, idx, f"{name} is neither clearly triangular nor sinusoidal: "
                          f"0.4 < SI {si:.2f} < 0.6")
