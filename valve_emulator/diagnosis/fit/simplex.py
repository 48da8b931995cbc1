"""Nelder–Mead on a handful of parameters: scipy's algorithm, step for step, in plain Python floats.

Every polish of the diagnosis minimises over one to five parameters (the time constants, a free dead time, a
candidate's parameters) in a few dozen cost evaluations, thousands of times per diagnosis. For such small
simplices the bookkeeping of ``scipy.optimize.minimize(method="Nelder-Mead")`` — numpy reductions, sorts and
copies of two-element arrays, a result object per iteration — cost about as much as a cost evaluation of a
10,000-sample record. :func:`nelder_mead` is the same algorithm (scipy 1.17's ``_minimize_neldermead`` with
``initial_simplex``, ``maxfev``, ``xatol`` and ``fatol``, not adaptive, no bounds): the same reflection,
expansion, contraction and shrink coefficients, the same arithmetic on the same numbers in the same order,
vertices ranked by the same ``numpy.argsort``, the same stopping tests — so it visits the same points and
returns the same minimum, bit for bit (``tests/diagnosis/fit/test_simplex.py`` compares it with scipy).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Minimum", "nelder_mead"]

# scipy's coefficients of the non-adaptive method: reflection, expansion, contraction, shrink.
_RHO, _CHI, _PSI, _SIGMA = 1, 2, 0.5, 0.5


@dataclass(frozen=True)
class Minimum:
    """Where :func:`nelder_mead` stopped: the best vertex ``x`` and its cost ``fun`` (NaN when any vertex's cost
    is NaN, as scipy reports it), ``start`` the cost of the initial simplex's first vertex (evaluated first)."""

    x: np.ndarray
    fun: float
    start: float


class _OutOfEvaluations(Exception):
    """The evaluation budget is spent (scipy's ``_MaxFuncCallError``)."""


def nelder_mead(cost: Callable[[np.ndarray], float], simplex: np.ndarray, *, maxfev: int, xatol: float,
                fatol: float) -> Minimum:
    """Minimise ``cost`` from the ``(N + 1, N)`` ``simplex`` with at most ``maxfev`` evaluations (see the module
    docstring). ``cost`` receives each point as a fresh float array."""
    sim = [[float(v) for v in row] for row in np.asarray(simplex, dtype=float)]
    n = len(sim[0])
    fsim = [float("inf")] * (n + 1)
    calls = 0

    def f(x: list[float]) -> float:
        nonlocal calls
        if calls >= maxfev:
            raise _OutOfEvaluations
        calls += 1
        return float(cost(np.array(x)))

    def ranked() -> None:
        if len(set(fsim)) == len(fsim) and all(v == v for v in fsim):
            # Distinct costs, none NaN: one order sorts them, numpy's argsort's too; Python's sort finds it without
            # building an array per iteration. Ties (and NaNs) keep numpy's own order.
            order = sorted(range(len(fsim)), key=fsim.__getitem__)
        else:
            order = np.argsort(np.array(fsim)).tolist()
        sim[:] = [sim[i] for i in order]
        fsim[:] = [fsim[i] for i in order]

    try:
        for k in range(n + 1):
            fsim[k] = f(sim[k])
    except _OutOfEvaluations:
        pass
    start = fsim[0]
    ranked()
    while calls < maxfev:
        try:
            if _converged(sim, fsim, xatol, fatol):
                break
            _step(sim, fsim, f, n)
        except _OutOfEvaluations:
            pass
        ranked()
    return Minimum(x=np.array(sim[0]), fun=float(np.min(np.array(fsim))), start=start)


def _converged(sim: list[list[float]], fsim: list[float], xatol: float, fatol: float) -> bool:
    """scipy's test: every vertex within ``xatol`` of the best in every coordinate and within ``fatol`` of its
    cost (a NaN difference fails it, as it makes numpy's maximum NaN)."""
    best, f0 = sim[0], fsim[0]
    return (all(abs(v - b) <= xatol for row in sim[1:] for v, b in zip(row, best))
            and all(abs(f0 - fv) <= fatol for fv in fsim[1:]))


def _step(sim: list[list[float]], fsim: list[float], f: Callable[[list[float]], float], n: int) -> None:
    """One iteration on the ranked simplex: reflect the worst vertex through the centroid of the others, then
    expand, contract outside or inside, or shrink towards the best vertex."""
    xbar = list(sim[0])
    for row in sim[1:-1]:                  # numpy's add.reduce over the rows: in order
        xbar = [a + b for a, b in zip(xbar, row)]
    xbar = [a / n for a in xbar]
    worst = sim[-1]
    xr = [(1 + _RHO) * a - _RHO * w for a, w in zip(xbar, worst)]
    fxr = f(xr)
    if fxr < fsim[0]:
        xe = [(1 + _RHO * _CHI) * a - _RHO * _CHI * w for a, w in zip(xbar, worst)]
        fxe = f(xe)
        sim[-1], fsim[-1] = (xe, fxe) if fxe < fxr else (xr, fxr)
        return
    if fxr < fsim[-2]:
        sim[-1], fsim[-1] = xr, fxr
        return
    if fxr < fsim[-1]:
        xc = [(1 + _PSI * _RHO) * a - _PSI * _RHO * w for a, w in zip(xbar, worst)]
        fxc = f(xc)
        if fxc <= fxr:
            sim[-1], fsim[-1] = xc, fxc
            return
    else:
        xcc = [(1 - _PSI) * a + _PSI * w for a, w in zip(xbar, worst)]
        fxcc = f(xcc)
        if fxcc < fsim[-1]:
            sim[-1], fsim[-1] = xcc, fxcc
            return
    for j in range(1, n + 1):
        sim[j] = [b + _SIGMA * (v - b) for v, b in zip(sim[j], sim[0])]
        fsim[j] = f(sim[j])
