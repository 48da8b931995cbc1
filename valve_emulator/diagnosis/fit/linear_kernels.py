r"""Compiled kernels of the batched linear fit (numba): all-pole filtering and least squares over dead times.

Arrays are time-major, ``(T, n)``, columns innermost — the layout the valve kernels produce — and the
parallel versions split the columns into blocks of :data:`_BLOCK` (contiguous in every row). The Python
entry points are :func:`~valve_emulator.diagnosis.fit.linear.filter_inputs` and
:func:`~valve_emulator.diagnosis.fit.linear.delay_grid_sse`; the maths is in that module's docstring.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["filter_columns", "grid_sse", "normal_equations"]

# Relative ridge on the normal equations: keeps a constant (uninformative) candidate column solvable
# without changing any well-posed fit beyond rounding.
RIDGE = 1e-10
# Fewer columns than this run serially: starting the thread pool costs more than it saves.
_PARALLEL_MIN = 16
# Columns per parallel task: a block is contiguous in every row of a time-major array.
_BLOCK = 32


@numba.njit(cache=True, inline="always")
def _filter_block(u, mean, c0, c1, alpha, gain, integ, dt, out):  # pragma: no cover - compiled
    # Time-major (T, n) arrays, columns innermost: the layout the valve kernels produce, so no transpose.
    T = u.shape[0]
    p = alpha.shape[0] - 1
    start = min(max(p, 1), T)
    for k in range(start):  # at rest for the first input: no transient when it is already settled
        for c in range(c0, c1):
            out[k, c] = u[0, c] - mean[c]
    for k in range(start, T):
        for c in range(c0, c1):
            s = gain * (u[k - 1, c] - mean[c])
            for i in range(1, p + 1):
                s -= alpha[i] * out[k - i, c]
            out[k, c] = s
    if integ:
        acc = np.zeros(c1 - c0)
        for k in range(T):
            for c in range(c0, c1):
                acc[c - c0] += dt * out[k, c]
                out[k, c] = acc[c - c0]


@numba.njit(cache=True, parallel=True)
def _filter_parallel(u, mean, alpha, gain, integ, dt, out):  # pragma: no cover - compiled
    n = u.shape[1]
    nblocks = (n + _BLOCK - 1) // _BLOCK
    for b in numba.prange(nblocks):
        _filter_block(u, mean, b * _BLOCK, min(n, (b + 1) * _BLOCK), alpha, gain, integ, dt, out)


@numba.njit(cache=True)
def _filter_serial(u, mean, alpha, gain, integ, dt, out):  # pragma: no cover - compiled
    _filter_block(u, mean, 0, u.shape[1], alpha, gain, integ, dt, out)


@numba.njit(cache=True, inline="always")
def _solve_sse(G, r, yy, q, beta):  # pragma: no cover - compiled
    """Cholesky solve of G beta = r (upper triangle of G filled); return yy - beta·r."""
    L = np.zeros((q, q))
    for i in range(q):
        for j in range(i + 1):
            s = G[j, i] if j <= i else G[i, j]
            if i == j:
                s += RIDGE * (G[i, i] + 1e-300)
            for m in range(j):
                s -= L[i, m] * L[j, m]
            if i == j:
                # A regressor (numerically) in the span of the earlier ones, e.g. a valve that never
                # moves: drop it (a huge pivot makes its coefficient zero) instead of dividing by ~0.
                L[i, i] = np.sqrt(s) if s > 1e-9 * (G[i, i] + 1e-300) else 1e150
            else:
                L[i, j] = s / L[j, j]
    w = np.empty(q)
    for i in range(q):
        s = r[i]
        for m in range(i):
            s -= L[i, m] * w[m]
        w[i] = s / L[i, i]
    for i in range(q - 1, -1, -1):
        s = w[i]
        for m in range(i + 1, q):
            s -= L[m, i] * beta[m]
        beta[i] = s / L[i, i]
    sse = yy
    for i in range(q):
        sse -= beta[i] * r[i]
    return max(sse, 0.0)


@numba.njit(cache=True, inline="always")
def _grid_block(c0, c1, z, y, w0, w1, delays, ntaps, trend, sums, sse, coef):  # pragma: no cover - compiled
    # Gram entries come from prefix sums (O(1) per delay); only the cross-correlation with PV costs
    # O(T) per lag, and neighbouring delays share lags: the work is (delays + taps - 1)·T per column.
    # Time-major z (T, n); a block of columns is processed together, columns innermost.
    T = z.shape[0]
    nb = c1 - c0
    nd = delays.shape[0]
    q = ntaps + 1 + trend
    dmin, dmax = delays.min(), delays.max()
    nlag = dmax - dmin + ntaps
    nw = w1 - w0
    yy, sy, ty, tt, st = sums[0], sums[1], sums[2], sums[3], sums[4]
    P = np.zeros((ntaps, T + 1, nb))      # P[l, m, j] = sum_{i<m} z[i] z[i-l]
    P1 = np.zeros((T + 1, nb))            # sum z
    PK = np.zeros((T + 1, nb))            # sum i z[i]
    for m in range(T):
        for j in range(nb):
            zm = z[m, c0 + j]
            P1[m + 1, j] = P1[m, j] + zm
            PK[m + 1, j] = PK[m, j] + m * zm
            for tap in range(ntaps):
                P[tap, m + 1, j] = P[tap, m, j] + (zm * z[m - tap, c0 + j] if m >= tap else 0.0)
    X = np.zeros((nlag, nb))              # X[i, j] = sum_k z[k - (dmin + i), j] y[k]
    for k in range(w0, w1):               # time outermost: the nlag rows in use stay in cache
        yk = y[k]
        for i in range(nlag):
            row = k - dmin - i
            for j in range(nb):
                X[i, j] += z[row, c0 + j] * yk
    G = np.zeros((q, q))
    r = np.zeros(q)
    beta = np.zeros(q)
    for j in range(nb):
        for di in range(nd):
            d = delays[di]
            for i in range(ntaps):
                a0, a1 = w0 - d - i, w1 - d - i          # index range of z for tap i
                for jj in range(i, ntaps):
                    G[i, jj] = P[jj - i, a1, j] - P[jj - i, a0, j]
                G[i, ntaps] = P1[a1, j] - P1[a0, j]
                if trend:
                    # sum_k (k/T) z[k-s] = sum_m (m+s) z[m] / T
                    s_ = d + i
                    G[i, ntaps + 1] = (PK[a1, j] - PK[a0, j] + s_ * (P1[a1, j] - P1[a0, j])) / T
                r[i] = X[d - dmin + i, j]
            G[ntaps, ntaps] = nw
            r[ntaps] = sy
            if trend:
                G[ntaps, ntaps + 1] = st
                G[ntaps + 1, ntaps + 1] = tt
                r[ntaps + 1] = ty
            sse[c0 + j, di] = _solve_sse(G, r, yy, q, beta)
            for i in range(q):
                coef[c0 + j, di, i] = beta[i]


@numba.njit(cache=True)
def _window_sums(y, w0, w1, T):  # pragma: no cover - compiled
    s = np.zeros(5)  # yy, sum y, sum t y, sum t^2, sum t  with t = k/T
    for k in range(w0, w1):
        t = k / T
        s[0] += y[k] * y[k]
        s[1] += y[k]
        s[2] += t * y[k]
        s[3] += t * t
        s[4] += t
    return s


@numba.njit(cache=True, parallel=True)
def _grid_parallel(z, y, w0, w1, delays, ntaps, trend, sse, coef):  # pragma: no cover - compiled
    sums = _window_sums(y, w0, w1, z.shape[0])
    n = z.shape[1]
    nblocks = (n + _BLOCK - 1) // _BLOCK
    for b in numba.prange(nblocks):
        _grid_block(b * _BLOCK, min(n, (b + 1) * _BLOCK), z, y, w0, w1, delays, ntaps, trend, sums, sse, coef)


@numba.njit(cache=True)
def _grid_serial(z, y, w0, w1, delays, ntaps, trend, sse, coef):  # pragma: no cover - compiled
    sums = _window_sums(y, w0, w1, z.shape[0])
    _grid_block(0, z.shape[1], z, y, w0, w1, delays, ntaps, trend, sums, sse, coef)


def filter_columns(u, mean, alpha, gain, integ, dt, out) -> None:
    """``out`` = the strictly causal, unit-DC-gain all-pole filter of ``u − mean`` (+ integrator), in place."""
    kernel = _filter_parallel if u.shape[1] >= _PARALLEL_MIN else _filter_serial
    kernel(u, mean, alpha, gain, integ, dt, out)


def grid_sse(z, y, w0, w1, delays, ntaps, trend, sse, coef) -> None:
    """Fill ``sse`` (n, nd) and ``coef`` (n, nd, q) for every column of ``z`` and every delay, in place."""
    kernel = _grid_parallel if z.shape[1] >= _PARALLEL_MIN else _grid_serial
    kernel(z, y, w0, w1, delays, ntaps, trend, sse, coef)


@numba.njit(cache=True)
def normal_equations(X, y):  # pragma: no cover - compiled
    """``(XᵀX, Xᵀy)`` of a tall, skinny least-squares problem, single-threaded.

    Why not ``X.T @ X``: numpy hands that to a multi-threaded BLAS, whose threads then compete with the
    compiled kernels' thread pool for the same cores; at 10⁴–10⁵ samples that contention doubled the
    diagnosis' run time. A plain loop over the rows is as fast for a handful of columns and never waits.
    """
    T, q = X.shape
    G = np.zeros((q, q))
    b = np.zeros(q)
    for k in range(T):
        yk = y[k]
        for i in range(q):
            xi = X[k, i]
            b[i] += xi * yk
            for j in range(i, q):
                G[i, j] += xi * X[k, j]
    for i in range(q):
        for j in range(i):
            G[i, j] = G[j, i]
    return G, b
