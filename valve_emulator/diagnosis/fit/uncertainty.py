r"""Parameter uncertainty from the cost surface (profile likelihood on the refinement grid).

With Gaussian errors, :math:`-2\ln L = N \ln(\mathrm{SSE}/N) + c`, so the set of parameter values whose
:math:`N \ln(\mathrm{SSE}/\mathrm{SSE}_{\min})` stays below the 95 % point of :math:`\chi^2_k` (k the
candidate's parameters, the linear part re-fitted at every point) is an approximate 95 % confidence region
(Wilks). Threshold parameters sit on boundaries and the cost is piecewise constant at fine scale, so the
region is approximate; its extent on each axis, widened by half a grid step, is the reported interval.
The held-out fit is the practical check that the interval is not optimistic.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from valve_emulator.diagnosis.fit.cost import relative_cost

__all__ = ["LEVEL", "intervals"]

#: Confidence level of the reported intervals.
LEVEL = 0.95


def intervals(params: np.ndarray, sse: np.ndarray, n: int, names: tuple[str, ...], k: int,
              *, axes: tuple[int, ...] | None = None) -> dict[str, tuple[float, float]]:
    """Interval ``(lo, hi)`` per parameter name from a surface of SSE over parameter rows.

    Parameters
    ----------
    params : (m, p) parameter rows of the surface.
    sse : (m,) fit-part SSE at each row.
    n : samples in the fit part.
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
