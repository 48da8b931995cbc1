r"""Parameter uncertainty from the cost surface (profile likelihood on the refinement grid).

With Gaussian errors, :math:`-2\ln L = N \ln(\mathrm{SSE}/N) + c`, so the set of parameter values whose
:math:`N \ln(\mathrm{SSE}/\mathrm{SSE}_{\min})` stays below the 95 % point of :math:`\chi^2_k` (k the
candidate's parameters, the linear part re-fitted at every point) is an approximate 95 % confidence region
(Wilks). Threshold parameters sit on boundaries and the cost is piecewise constant at fine scale, so the
region is approximate; its extent on each axis, widened by half a grid step, is the reported interval.
The held-out fit is the practical check that the interval is not optimistic.

The χ² bound assumes independent errors. A closed loop's residual is not: a wandering load, a plant the
model matches only approximately and a friction law that is not the search's leave an error that is smooth over
many samples, and N samples then carry the information of far fewer. The cost is therefore scaled by the
residual's effective fraction (:func:`effective_fraction`, N_eff/N = 1/τ_int, the integrated autocorrelation
time) before it is compared with χ²; on the drawn sticky loops of the independent simulator
(:mod:`~valve_emulator.benchmark.independent`) N_eff is one to five per cent of N, and without this scaling
the intervals were ten times too narrow.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from valve_emulator.diagnosis.fit.cost import relative_cost

__all__ = ["LEVEL", "effective_fraction", "intervals", "touches_edge"]

#: Confidence level of the reported intervals.
LEVEL = 0.95


def effective_fraction(residual: np.ndarray) -> float:
    """N_eff / N of a residual series: 1/τ_int, with τ_int = 1 + 2 Σ ρ_k its integrated autocorrelation time.

    The sum runs over Geyer's (1992) initial positive sequence (pairs ρ_{2m−1} + ρ_{2m} while they are
    positive), the usual estimator for a series whose correlation dies out; it is never taken below the AR(1)
    value (1 + ρ₁)/(1 − ρ₁), which it equals for an AR(1) series. The fraction lies in [1/N, 1].
    """
    r = np.asarray(residual, dtype=float)
    n = r.size
    if n < 4:
        return 1.0
    r = r - r.mean()
    var = float(r @ r)
    if var <= 0.0:
        return 1.0
    spectrum = np.abs(np.fft.rfft(r, 2 * n)) ** 2  # autocovariances by FFT (Wiener–Khinchin), zero-padded
    rho = np.fft.irfft(spectrum)[1:n] / var
    total = 0.0
    for m in range(0, rho.size - 1, 2):
        pair = rho[m] + rho[m + 1]
        if pair <= 0.0:
            break
        total += pair
    rho1 = float(np.clip(rho[0], 0.0, 1.0 - 1e-9))
    tau = max(1.0 + 2.0 * total, (1.0 + rho1) / (1.0 - rho1))
    return float(min(1.0, max(1.0 / tau, 1.0 / n)))


def touches_edge(params: np.ndarray, sse: np.ndarray, n: float, k: int, axis: int) -> tuple[bool, bool]:
    """Whether the 95 % region of a surface reaches the (lowest, highest) value of ``params[:, axis]``: the
    surface then cuts the interval there, and a wider one is needed to say where it ends."""
    inside = relative_cost(sse, n) <= chi2.ppf(LEVEL, k)
    sel = params[inside, axis]
    col = params[:, axis]
    return bool(sel.min() <= col.min()), bool(sel.max() >= col.max())


def intervals(params: np.ndarray, sse: np.ndarray, n: float, names: tuple[str, ...], k: int,
              *, axes: tuple[int, ...] | None = None) -> dict[str, tuple[float, float]]:
    """Interval ``(lo, hi)`` per parameter name from a surface of SSE over parameter rows.

    Parameters
    ----------
    params : (m, p) parameter rows of the surface.
    sse : (m,) fit-part SSE at each row.
    n : samples in the fit part, or their effective number (:func:`effective_fraction`).
    names : names of the columns of ``params`` to report.
    k : number of free parameters (degrees of freedom of the chi-square).
    axes : columns of ``params`` to report (default: the first ``len(names)``).
    """
    axes = tuple(range(len(names))) if axes is None else axes
    inside = relative_cost(sse, n) <= chi2.ppf(LEVEL, k)
    out = {}
    for name, ax in zip(names, axes):
        values = np.unique(params[:, ax])
        step = float(np.min(np.diff(values))) if values.size > 1 else 0.0
        sel = params[inside, ax]
        out[name] = (float(sel.min() - step / 2), float(sel.max() + step / 2))
    return out
