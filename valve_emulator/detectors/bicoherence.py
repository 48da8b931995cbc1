r"""Bicoherence non-Gaussianity and nonlinearity indices, with ellipse-fitted "apparent stiction".

M. A. A. S. Choudhury, S. L. Shah, N. F. Thornhill, "Diagnosis of poor control-loop performance using
higher-order statistics", Automatica 40 (2004) 1719–1728; the ellipse: M. A. A. S. Choudhury, N. F. Thornhill,
S. L. Shah, "Modelling valve stiction", Control Engineering Practice 13 (2005) 641–658. A linear loop driven by
Gaussian noise has a flat, near-zero bicoherence; a sticky valve is a nonlinearity that couples the phases of
the oscillation's harmonics and raises the bicoherence at a few frequency pairs.

Squared bicoherence (Kim–Powers normalisation), estimated by averaging ``K`` Hann-windowed FFT segments of
``nfft`` = 64 samples overlapping by half, over the principal domain :math:`0 < f_2 \le f_1`,
:math:`f_1 + f_2 < f_s/2` (``L`` bifrequencies):

.. math::  \widehat{bic}^2(f_1, f_2) = \frac{|\frac1K\sum X_k(f_1) X_k(f_2) X_k^*(f_1+f_2)|^2}
           {\frac1K\sum |X_k(f_1) X_k(f_2)|^2 \;\frac1K\sum |X_k(f_1+f_2)|^2}

For a Gaussian signal :math:`2K\,\widehat{bic}^2` is about :math:`\chi^2_2`, so the domain average is tested
against :math:`\chi^2_{2L}`:

.. math::  NGI = \overline{\widehat{bic}^2} - \frac{\chi^2_{2L,\,0.95}}{2KL}, \qquad
           NLI = \Big|\widehat{bic}^2_{max} - \big(\overline{\widehat{bic}^2}_{rob} +
           2\,\hat\sigma_{rob}\big)\Big|

(robust mean and standard deviation over the values left after dropping the largest and smallest 10 %). The
signal is non-Gaussian when **NGI > 0.001** and nonlinear when also **NLI > 0.01**: the commonly quoted values of
Choudhury et al.; the NGI written here is the form with a test on the domain average given in Choudhury, Shah &
Thornhill's book (Diagnosis of Process Nonlinearities and Valve Stiction, Springer 2008) as recalled, not
re-checked against the 2004 text.

Procedure as implemented: the signal is the control error ``sp − pv`` (``pv`` without a set point), linearly
detrended. When it oscillates regularly (Thornhill et al. 2003, see :mod:`~valve_emulator.detectors.base`)
with a period above 32 samples it is low-pass filtered (ideal filter at the new Nyquist frequency) and decimated
to about 16 samples per period (but to no fewer than 320 samples), so that the oscillation and its first
harmonics fall inside the 64-point spectrum; this resampling rule is this project's, chosen once.
Bifrequencies touching a bin without power (below 1e-10 of the largest) are left out of the domain, where the
published estimator adds a small constant to the denominator for the same purpose. A nonlinear, regularly
oscillating loop is called stiction and its apparent stiction is the OP-axis width of the ellipse fitted to OP
and PV, both band-pass filtered to 0.5–1.5 times the oscillation frequency (zero-phase, in the frequency
domain). A nonlinear loop without a regular oscillation is "undetermined"; a Gaussian or linear one is "no stiction".

Known behaviour: a clean, nearly symmetric limit cycle (the proof cases' concentration loop with S = 5, J = 2)
has little quadratic phase coupling, and its NGI sits within a few hundredths of zero either way depending on the
noise realisation, so the verdict there is a coin toss; an asymmetric cycle (overshoot, J > S) is found every
time. The NGI of a few-segment estimate (K = 22 for a 751-sample window) is coarse: coloured Gaussian noise
exceeds the 0.001 margin in about one window in six to ten. These are properties of the test on short windows,
not corrected here.
"""

from __future__ import annotations

from typing import Final

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal, stats

from valve_emulator.detectors.base import (
    MIN_SAMPLES,
    NO_STICTION,
    STICTION,
    UNDETERMINED,
    DetectorResult,
    oscillation,
    prepare,
)
from valve_emulator.detectors.ellipse import fit_ellipse, width_along_x

__all__ = ["bicoherence", "squared_bicoherence", "gaussianity_indices", "NGI_THRESHOLD", "NLI_THRESHOLD", "NFFT"]

NGI_THRESHOLD: Final = 0.001
NLI_THRESHOLD: Final = 0.01
NFFT: Final = 64
ALPHA: Final = 0.05
NAME: Final = "bicoherence"
_ROBUST_TRIM: Final = 0.10
_SAMPLES_PER_PERIOD: Final = 16
_MIN_DECIMATED: Final = 5 * NFFT
_POWER_FLOOR: Final = 1e-10


def squared_bicoherence(x: ArrayLike, *, nfft: int = NFFT) -> tuple[np.ndarray, int]:
    """Squared bicoherence over the principal domain (flat array of ``L`` values) and the segment count K.

    Bifrequencies touching a bin whose power is below 1e-10 of the largest are left out (see the code).
    """
    x = np.asarray(x, dtype=float)
    hop = nfft // 2
    starts = np.arange(0, x.size - nfft + 1, hop)
    if starts.size < 2:
        raise ValueError(f"squared_bicoherence needs at least {nfft + hop} samples, got {x.size}")
    seg = x[starts[:, None] + np.arange(nfft)[None, :]]
    seg = (seg - seg.mean(axis=1, keepdims=True)) * np.hanning(nfft)[None, :]
    spec = np.fft.fft(seg, axis=1)
    f1, f2 = np.meshgrid(np.arange(1, nfft // 2), np.arange(1, nfft // 2), indexing="ij")
    keep = (f2 <= f1) & (f1 + f2 < nfft // 2)
    i1, i2 = f1[keep], f2[keep]
    x1, x2, x3 = spec[:, i1], spec[:, i2], spec[:, i1 + i2]
    num = np.abs(np.mean(x1 * x2 * np.conj(x3), axis=0)) ** 2
    power = np.mean(np.abs(spec) ** 2, axis=0)
    # Bins without power (below round-off, e.g. above a filter's cut-off) give 0/0 ratios that can come out
    # near 1; they carry no information and are left out of the domain (Choudhury et al. add a small constant
    # to the denominator for the same reason).
    live = power > _POWER_FLOOR * power[1: nfft // 2].max()
    ok = live[i1] & live[i2] & live[i1 + i2]
    den = np.mean(np.abs(x1 * x2) ** 2, axis=0) * power[i1 + i2]
    return num[ok] / den[ok], int(starts.size)


def gaussianity_indices(bic2: np.ndarray, k: int) -> tuple[float, float]:
    """``(NGI, NLI)`` of squared-bicoherence values from ``k`` segments (module docstring)."""
    n = bic2.size
    crit = stats.chi2.ppf(1.0 - ALPHA, 2 * n) / (2.0 * k * n)
    ngi = float(np.mean(bic2) - crit)
    s = np.sort(bic2)
    cut = int(_ROBUST_TRIM * n)
    core = s[cut: n - cut] if n - 2 * cut >= 2 else s
    nli = float(abs(s[-1] - (core.mean() + 2.0 * core.std(ddof=1))))
    return ngi, nli


def _lowpass(x: np.ndarray, f_hi: float) -> np.ndarray:
    spec = np.fft.rfft(x)
    spec[np.fft.rfftfreq(x.size) > f_hi] = 0.0
    return np.fft.irfft(spec, x.size)


def _bandpass(x: np.ndarray, f_lo: float, f_hi: float) -> np.ndarray:
    spec = np.fft.rfft(x - x.mean())
    f = np.fft.rfftfreq(x.size)
    spec[(f < f_lo) | (f > f_hi)] = 0.0
    return np.fft.irfft(spec, x.size)


def bicoherence(op: ArrayLike, pv: ArrayLike, *, dt: float, sp: ArrayLike | None = None,
                integrating: bool = False) -> DetectorResult:
    """Choudhury et al.'s (2004) NGI/NLI test with ellipse-fitted apparent stiction; see the module docstring.

    Parameters
    ----------
    op, pv : controller output (%) and process value, equal length, finite.
    dt : sample time, s.
    sp : set point (optional; the error ``sp − pv`` is analysed when it is finite everywhere).
    integrating : accepted for a uniform signature; the test is the same for both kinds of process.

    Returns
    -------
    DetectorResult
        ``indices``: ``ngi``, ``nli``, ``segments`` (K), ``decimation``, ``period_s``, ``regularity`` and, when
        stiction is called, ``apparent_stiction`` (% of OP).
    """
    op, pv, s = prepare(op, pv, sp, dt)
    if op.size < MIN_SAMPLES:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{op.size} samples, at least {MIN_SAMPLES} needed")
    e = pv if s is None else s - pv
    if np.ptp(e) == 0:
        return DetectorResult(NAME, UNDETERMINED, {}, "the control error is constant")
    e = signal.detrend(e)
    osc = oscillation(e)
    q = 1
    if osc.regular and osc.period > 2 * _SAMPLES_PER_PERIOD:
        q = max(1, min(int(osc.period // _SAMPLES_PER_PERIOD), e.size // _MIN_DECIMATED))
    x = _lowpass(e, 0.5 / q)[::q] if q > 1 else e
    if x.size < NFFT + NFFT // 2:
        return DetectorResult(NAME, UNDETERMINED, {}, f"{x.size} samples after decimation, at least "
                              f"{NFFT + NFFT // 2} needed")
    bic2, k = squared_bicoherence(x)
    if bic2.size < 10:
        return DetectorResult(NAME, UNDETERMINED, {}, "the error has power at too few frequencies")
    ngi, nli = gaussianity_indices(bic2, k)
    idx = {"ngi": ngi, "nli": nli, "segments": k, "decimation": q, "period_s": osc.period * dt,
           "regularity": osc.regularity}
    if ngi <= NGI_THRESHOLD:
        return DetectorResult(NAME, NO_STICTION, idx, f"Gaussian, so linear: NGI {ngi:.4f} <= 0.001")
    if nli <= NLI_THRESHOLD:
        return DetectorResult(NAME, NO_STICTION, idx, f"non-Gaussian but linear: NLI {nli:.4f} <= 0.01")
    if not osc.regular:
        return DetectorResult(NAME, UNDETERMINED, idx, f"nonlinear (NGI {ngi:.4f}, NLI {nli:.3f}) but no "
                              f"regular oscillation to fit an ellipse to (regularity {osc.regularity:.2f})")
    f0 = 1.0 / osc.period
    conic = fit_ellipse(_bandpass(op, 0.5 * f0, 1.5 * f0), _bandpass(pv, 0.5 * f0, 1.5 * f0))
    width = width_along_x(conic) if conic is not None else float("nan")
    idx["apparent_stiction"] = width
    return DetectorResult(NAME, STICTION, idx, f"nonlinear and oscillating: NGI {ngi:.4f} > 0.001, NLI "
                          f"{nli:.3f} > 0.01; apparent stiction {width:.3g} % of OP")
