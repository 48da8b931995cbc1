r"""Parameter uncertainty from the cost surface (profile likelihood on the refinement grid).

With Gaussian errors, :math:`-2\ln L = N \ln(\mathrm{SSE}/N) + c`, so the set of parameter values whose
:math:`N \ln(\mathrm{SSE}/\mathrm{SSE}_{\min})` stays below the 95 % point of :math:`\chi^2_k` (k the
candidate's parameters, the linear part re-fitted at every point) is an approximate 95 % confidence region
(Wilks). Threshold parameters sit on boundaries and the cost is piecewise constant at fine scale, so the
region is approximate. On each axis the interval ends where the profile of the cost along that axis crosses
the bound, interpolated linearly between the last grid value inside the region and the first one outside
(:func:`intervals`), and never less than half a grid step beyond the last one inside: the grid says no more than
that.

The χ² bound assumes independent errors. A closed loop's residual is not: a wandering load, a plant the
model matches only approximately and a friction law that is not the search's leave an error that is smooth over
many samples, and N samples then carry the information of far fewer. The cost is therefore scaled by the
residual's effective fraction (:func:`effective_fraction`, N_eff/N = 1/τ_int, the integrated autocorrelation
time) before it is compared with χ²; on the drawn sticky loops of the independent simulator
(:mod:`~valve_emulator.benchmark.independent`) N_eff is one to five per cent of N, and without this scaling
the intervals were ten times too narrow.

Both assume the search's model is the plant's. Where it is not (a friction law, an actuator lag or a load the
model does not have), the cost surface is shaped by the mismatch as much as by the noise, and the bias it leaves
in the estimate changes along the record with the operating point and the load. The record itself shows how
much, by the delete-a-block jackknife (Künsch, *Ann. Statist.* 17, 1989), which needs no error model: the fit
part is cut into :data:`BLOCKS` consecutive blocks, the profile grid is scored on each with the linear part
re-fitted on that block alone, the estimate is taken again with each block left out (:func:`left_out`; among
the values the whole record allows at 99.9 %), and the spread of those B estimates gives the standard error
:math:`\mathrm{se}^2 = \tfrac{B-1}{B}\sum_b (\hat\theta_{(b)} - \bar\theta)^2`. The interval is widened to
hold :math:`\hat\theta \pm t_{B-1}\,\mathrm{se}` (:func:`jackknifed`). Where the model matches the plant the
blocks agree and this changes nothing. It is applied with a nominal model only: without one, a linear part
identified per block can stand in for the valve (``explain/findings.py``). On 40 drawn sticky loops with their
model (``tests/diagnosis/explain/test_interval_coverage.py``) the jackknife and the interpolated ends brought the
intervals of S from 27 to 29 covering of 32, their median width from 73 to 75 % of S.
"""

from __future__ import annotations

import numpy as np
from scipy import special

from valve_emulator.diagnosis.fit.cost import relative_cost

__all__ = ["BLOCKS", "LEVEL", "PLAUSIBLE", "block_windows", "chi2_quantile", "effective_fraction", "intervals",
           "jackknifed", "left_out", "optimum", "plausible", "student_t_quantile", "touches_edge"]


def chi2_quantile(p: float, k: int) -> float:
    """The ``p`` quantile of the chi-square distribution with ``k`` degrees of freedom.

    Computed as ``scipy.stats.chi2.ppf`` computes it (``2 * gammaincinv(k/2, p)``, the same bits) from
    :mod:`scipy.special`, without importing :mod:`scipy.stats`, whose import costs a first diagnosis ~0.3 s."""
    return float(2 * special.gammaincinv(k / 2, p))


def student_t_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of Student's t with ``dof`` degrees of freedom: ``scipy.stats.t.ppf``'s own
    computation (``stdtrit(dof, p)``, the same bits), from :mod:`scipy.special` (see :func:`chi2_quantile`)."""
    return float(special.stdtrit(dof, p))

#: Confidence level of the reported intervals.
LEVEL = 0.95
#: Consecutive blocks of the fit part left out in turn by the jackknife (:func:`jackknifed`).
BLOCKS = 8
#: Level of the profile region within which a left-out estimate is sought (:func:`left_out`).
PLAUSIBLE = 0.999


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
    inside = relative_cost(sse, n) <= chi2_quantile(LEVEL, k)
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

    Each end lies where the cost, minimised over the other columns, crosses the bound between the last value of
    the column inside the region and the next one (interpolated linearly; at least half a step beyond the last
    inside), or half a step beyond the grid where the region reaches its end.
    """
    axes = tuple(range(len(names))) if axes is None else axes
    cost = relative_cost(sse, n)
    bound = chi2_quantile(LEVEL, k)
    out = {}
    for name, ax in zip(names, axes):
        values, along = _along(params, cost, ax)
        half = float(np.min(np.diff(values))) / 2 if values.size > 1 else 0.0
        inside = np.flatnonzero(along <= bound)
        lo, hi = int(inside[0]), int(inside[-1])
        out[name] = (float(values[lo] - _beyond(values, along, bound, lo, -1, half)),
                     float(values[hi] + _beyond(values, along, bound, hi, +1, half)))
    return out


def _along(params: np.ndarray, cost: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """The profile of ``cost`` along column ``axis`` of ``params``: the column's distinct values, ascending, and
    the least cost over the rows at each (the other columns minimised out)."""
    values, which = np.unique(params[:, axis], return_inverse=True)
    along = np.full(values.size, np.inf)
    np.minimum.at(along, which, cost)
    return values, along


def _beyond(values: np.ndarray, along: np.ndarray, bound: float, i: int, way: int, half: float) -> float:
    """How far beyond ``values[i]`` (the last value inside, going ``way``) the cost ``along`` crosses ``bound``."""
    j = i + way
    if j < 0 or j >= values.size:
        return half
    gap = abs(float(values[j] - values[i]))
    rise = along[j] - along[i]
    share = (bound - along[i]) / rise if np.isfinite(rise) and rise > 0 else 1.0
    return float(max(half, min(1.0, share) * gap))


def block_windows(window: tuple[int, int], blocks: int = BLOCKS) -> list[tuple[int, int]]:
    """``window`` cut into ``blocks`` consecutive windows of (nearly) equal length."""
    edges = np.linspace(window[0], window[1], blocks + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def optimum(params: np.ndarray, sse: np.ndarray, axis: int) -> float:
    """Where the profile of ``sse`` along column ``axis`` of ``params`` is least: the grid value with the least
    SSE (over the other columns), refined to the vertex of the parabola through it and its two neighbours.

    On a grid the left-out estimates of the jackknife would otherwise move by whole steps, and one block that
    tips the choice between two neighbouring values would read as a spread of a step.
    """
    values, along = _along(params, sse, axis)
    i = int(np.argmin(along))
    if i == 0 or i == values.size - 1 or not np.all(np.isfinite(along[i - 1:i + 2])):
        return float(values[i])
    (x0, x1, x2), (y0, y1, y2) = values[i - 1:i + 2], along[i - 1:i + 2]
    return float(np.clip(_vertex(x0, x1, x2, y0, y1, y2), x0, x2))


def _vertex(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    """The abscissa of the vertex of the parabola through three points (the middle one for a line)."""
    num = (x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)
    den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
    return float(x1 - 0.5 * num / den) if den != 0.0 else float(x1)


def plausible(sse: np.ndarray, n: float, k: int) -> np.ndarray:
    """The rows of a surface the whole record does not exclude at the :data:`PLAUSIBLE` level (a mask)."""
    return relative_cost(sse, n) <= chi2_quantile(PLAUSIBLE, k)


def left_out(params: np.ndarray, block_sse: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """The estimates with each block left out (B, len(axes)): per block b, the :func:`optimum` along each of
    ``axes`` of the SSE summed over the other blocks (``block_sse`` (B, m): each block's SSE at each row of
    ``params`` (m, p)).

    Each block's linear part is its own, so the sum over blocks is a more pliable model than the whole record's
    (an offset per block can stand in for a valve that never moves): ``params`` should hold only the rows the
    whole record allows (:func:`plausible`), so that the jackknife measures how the estimate moves among them.
    """
    others = block_sse.sum(axis=0)[None, :] - block_sse
    return np.array([[optimum(params, row, ax) for ax in axes] for row in others])


def jackknifed(ivs: dict[str, tuple[float, float]], estimate: dict[str, float], left: np.ndarray,
               names: tuple[str, ...]) -> dict[str, tuple[float, float]]:
    """``ivs`` widened to hold ``estimate ± t_{B−1} se`` per name, se the delete-a-block jackknife's standard
    error from the ``left``-out estimates (B, len(names), column i for ``names[i]``; see the module docstring).
    Names without an interval are left out; fewer than two blocks change nothing."""
    out = dict(ivs)
    b = left.shape[0]
    if b < 2:
        return out
    t = student_t_quantile(0.5 + LEVEL / 2, b - 1)
    for i, name in enumerate(names):
        if name not in out:
            continue
        col = left[:, i]
        se = float(np.sqrt((b - 1) / b * np.sum((col - col.mean()) ** 2)))
        lo, hi = out[name]
        out[name] = (float(min(lo, estimate[name] - t * se)), float(max(hi, estimate[name] + t * se)))
    return out
