r"""Compiled kernel of the batched linear fit (numba): filtering and least squares over dead times, in one pass.

:func:`grid_sse` streams every input column once through the regressor filter (all-pole part, integrator,
high-pass prefilter, fractional delay) and, in the same pass, accumulates what the normal equations of every
dead time need — so the filtered inputs never exist as a (T, n) array. Memory traffic, not arithmetic, bounded
the earlier two-kernel version (filter everything, then fit everything): at 10⁴ samples × 512 columns each
intermediate array is 40 MB.

How the normal equations of all dead times come from one pass: the Gram entries
:math:`\sum_{k=w_0}^{w_1-1} z_{k-d-i} z_{k-d-j}` are differences of running sums
:math:`P_l(m) = \sum_{i<m} z_i z_{i-l}` taken at two short runs of indices (one near :math:`w_0`, one near
:math:`w_1`), so only those runs are kept; the cross terms :math:`\sum_k z_{k-d-i} y_k` need the last
``dmax + taps`` filtered values, kept in a ring buffer. The work is (delays + taps − 1)·T per column.

The pass, per block of :data:`_BLOCK` columns (:func:`_grid_block`), makes each sample of z (all-pole part,
integrator, prefilter, fractional delay), adds it to the running sums and, every :data:`_TILE` samples, to the
cross terms; then :func:`_solve_column` assembles and solves each column's normal equations for every dead time.

The kernel is serial and releases the GIL; :func:`grid_sse` splits the columns over
``numba.get_num_threads()`` Python threads. A single-threaded compiled function compiles in a fraction of the
time of a ``parallel=True`` one, and this is the kernel a fresh install compiles first.

The Python entry points are :func:`~valve_emulator.diagnosis.fit.linear.input_grid_sse` and
:func:`~valve_emulator.diagnosis.fit.linear.delay_grid_sse`; the maths is in that module's docstring.
"""

from __future__ import annotations

import numba
import numpy as np

from valve_emulator.diagnosis._threads import run_split, workers_for
from valve_emulator.physics._arrays import kernel_array

__all__ = ["RIDGE", "column_mean", "column_means", "column_sse", "grid_sse", "normal_equations",
           "normal_equations_rows"]

# Relative ridge on the normal equations: keeps a constant (uninformative) candidate column solvable
# without changing any well-posed fit beyond rounding.
RIDGE = 1e-10
# Columns processed together in the time loop (one row of the ring buffer stays in a cache line or two).
_BLOCK = 128
# Samples whose cross terms with the output are accumulated together (see add_cross_tile in _grid_block: eight
# products per element in a register; sixteen made each element's chain of additions the bound, 0.8× the speed).
_TILE = 8
# Columns of a wider input scored together, from a contiguous copy (see grid_sse): read in place, each block is a
# short run of every long row (2 KB apart for 256 columns) and the pass over time waited on those reads; from a
# copy of 64 columns, copy included, a 256-column input scored in 0.4 of the time at 10⁴ samples (fresh data,
# two threads).
_GROUP = 64
# Fewest systems solved side by side where a grid column has fewer dead times (_grid_block): the columns of a block
# are taken together until there are this many, so that the loops over the systems are long enough to vectorise.
_SYSTEMS = 64

@numba.njit(cache=True, nogil=True)
def _solve_sses(G, r, yy, q, ntaps, sign, held, room, out):  # pragma: no cover - compiled
    """For each n: Cholesky solve of G[:, :, n] beta = r[:, n] (upper triangle of G filled); ``out[n]`` = yy - beta·r.

    The systems are independent (one per dead time of a grid column), and each is solved with its own numbers
    through the operations written for one system — the same products, sums, divisions and square roots in the
    same order, so the same bits — but stage by stage over all of them (each entry of the factor, of the forward
    and of the back substitution for every system before the next entry): one system's solve is a chain of
    about a dozen dependent divisions and square roots, which left alone kept the core waiting on each (about
    80 ns per system at q = 3, and two allocations); side by side the systems' chains overlap. ``room``
    (:func:`_solve_room`): the factor, the forward and back substitutions and the taps' flags, allocated once by
    the caller; every entry read is written first.

    With ``sign`` (+1 or −1; 0: free) the sum of the first ``ntaps`` coefficients (the gain) must have that
    sign: when the free solution's does not, the constrained least-squares optimum has gain 0 (a single
    linear inequality is active or not), whose SSE exceeds the free one by ``(cᵀβ)² / (cᵀG⁻¹c)``, c the
    indicator of the taps (Lawson & Hanson, *Solving Least Squares Problems*, ch. 20).

    With ``held`` (not NaN) the gain is held there instead (``sign`` is then moot): the equality-constrained
    optimum's SSE exceeds the free one by ``(cᵀβ − held)² / (cᵀG⁻¹c)`` (the same theorem). A column whose taps
    all drop out (it never moves) is fitted by the offset alone whatever the gain, and scores the free SSE."""
    L, w, beta, moves = room
    N = out.shape[0]
    for n in range(N):
        moves[n] = False
    for i in range(q):
        for j in range(i + 1):
            if i == j:
                for n in range(N):
                    s = G[i, i, n]
                    s += RIDGE * (G[i, i, n] + 1e-300)
                    for m in range(j):
                        s -= L[i, m, n] * L[j, m, n]
                    # A regressor (numerically) in the span of the earlier ones, e.g. a valve that never
                    # moves: drop it (a huge pivot makes its coefficient zero) instead of dividing by ~0.
                    L[i, i, n] = np.sqrt(s) if s > 1e-9 * (G[i, i, n] + 1e-300) else 1e150
                    moves[n] = moves[n] or (i < ntaps and L[i, i, n] != 1e150)
            else:
                for n in range(N):
                    s = G[j, i, n]
                    for m in range(j):
                        s -= L[i, m, n] * L[j, m, n]
                    L[i, j, n] = s / L[j, j, n]
    for i in range(q):
        for n in range(N):
            s = r[i, n]
            for m in range(i):
                s -= L[i, m, n] * w[m, n]
            w[i, n] = s / L[i, i, n]
    for i in range(q - 1, -1, -1):
        for n in range(N):
            s = w[i, n]
            for m in range(i + 1, q):
                s -= L[m, i, n] * beta[m, n]
            beta[i, n] = s / L[i, i, n]
    for n in range(N):
        sse = yy
        for i in range(q):
            sse -= beta[i, n] * r[i, n]
        g = 0.0
        for i in range(ntaps):
            g += beta[i, n]
        if held == held:
            gap = g - held if moves[n] else 0.0
        else:
            gap = g if sign * g < 0.0 else 0.0
        if gap != 0.0:
            # c^T G^-1 c = |L^-1 c|^2, c = (1, …, 1, 0, …) over the taps.
            cgc = 0.0
            for i in range(q):
                s = 1.0 if i < ntaps else 0.0
                for m in range(i):
                    s -= L[i, m, n] * w[m, n]
                w[i, n] = s / L[i, i, n]
                cgc += w[i, n] * w[i, n]
            if cgc > 0.0:
                sse += gap * gap / cgc
        out[n] = max(sse, 0.0)


@numba.njit(cache=True, nogil=True)
def _solve_room(q, n):  # pragma: no cover - compiled
    """Room for :func:`_solve_sses` of ``n`` systems of size ``q``: the factor L (its strictly upper triangle never
    read), the forward and back substitutions, and whether a tap moves."""
    return np.zeros((q, q, n)), np.zeros((q, n)), np.zeros((q, n)), np.zeros(n, dtype=np.bool_)


@numba.njit(cache=True, nogil=True)
def _ring(n):  # pragma: no cover - compiled
    """Size (a power of two, at least ``n``) and index mask of a ring buffer."""
    size = 1
    while size < n:
        size *= 2
    return size, size - 1


@numba.njit(cache=True, nogil=True)
def _filter_setup(alpha, T):  # pragma: no cover - compiled
    """Order p, DC gain sum(alpha) and first recursive sample of the all-pole filter, and the ring of its past
    outputs."""
    p = alpha.shape[0] - 1
    gain = 0.0
    for i in range(p + 1):
        gain += alpha[i]
    rring, rmask = _ring(p + 1)
    return p, gain, min(max(p, 1), T), rring, rmask


@numba.njit(cache=True, nogil=True)
def _keep(row, P, P1, PK, keepP, keepP1, keepPK):  # pragma: no cover - compiled
    """Copy the running sums into row ``row`` of a kept run."""
    for j in range(P1.shape[0]):
        keepP1[row, j] = P1[j]
        keepPK[row, j] = PK[j]
        for tap in range(P.shape[0]):
            keepP[tap, row, j] = P[tap, j]


@numba.njit(cache=True, nogil=True)
def _window_sums(y, w0, w1, T):  # pragma: no cover - compiled
    """Sums over the fit window of y and of the trend t = k/T: (Σy², Σy, Σty, Σt², Σt)."""
    yy = sy = ty = tt = st = 0.0
    for k in range(w0, w1):
        t = k / T
        yy += y[k] * y[k]
        sy += y[k]
        ty += t * y[k]
        tt += t * t
        st += t
    return yy, sy, ty, tt, st


@numba.njit(cache=True, nogil=True)
def _column_means(u):  # pragma: no cover - compiled
    """Mean over all T samples of each column of ``u`` (T, n), summed in time order."""
    T, n = u.shape
    mean = np.zeros(n)
    for k in range(T):
        for j in range(n):
            mean[j] += u[k, j]
    for j in range(n):
        mean[j] /= T
    return mean


def column_means(u: np.ndarray) -> np.ndarray:
    """The column means :func:`grid_sse` subtracts from its input ``u`` (T, n) before filtering: computed once,
    they serve every structure a block of inputs is scored for. On a long record reading the block for its means
    costs as much as the pass that fits it (at 10^5 samples 64 columns are 51 MB, more than the cache holds)."""
    return _column_means(kernel_array(u))


@numba.njit(cache=True, nogil=True)
def _column_systems(j, lo, hi, X, sums, fit, T, dmin, dmax, G, r, at):  # pragma: no cover - compiled
    """The normal equations of column ``j`` for every dead time, from the running sums kept near w0 (``lo``) and
    w1 (``hi``), the cross terms ``X`` and the window ``sums``: system ``at + di`` of ``G`` (q, q, ·) and ``r``
    (q, ·) for dead time ``di``."""
    _, w0, w1, delays, ntaps, trend, _, _ = fit
    _, sy, ty, tt, st = sums
    loP, loP1, loPK = lo
    hiP, hiP1, hiPK = hi
    for di_ in range(delays.shape[0]):
        d = delays[di_]
        di = at + di_
        for i in range(ntaps):
            o = dmax - d + ntaps - 1 - i     # a0 - lo0 = a1 - hi0, with a0 = w0 - d - i, a1 = w1 - d - i
            for jj in range(i, ntaps):
                G[i, jj, di] = hiP[jj - i, o, j] - loP[jj - i, o, j]
            G[i, ntaps, di] = hiP1[o, j] - loP1[o, j]
            if trend:
                # sum_k (k/T) z[k-s] = sum_m (m+s) z[m] / T
                s_ = d + i
                G[i, ntaps + 1, di] = (hiPK[o, j] - loPK[o, j] + s_ * (hiP1[o, j] - loP1[o, j])) / T
            r[i, di] = X[d - dmin + i, j]
        G[ntaps, ntaps, di] = w1 - w0
        r[ntaps, di] = sy
        if trend:
            G[ntaps, ntaps + 1, di] = st
            G[ntaps + 1, ntaps + 1, di] = tt
            r[ntaps + 1, di] = ty


@numba.njit(cache=True, nogil=True)
def _kept_run(ntaps, nlag, nb):  # pragma: no cover - compiled
    """Room for a run of ``nlag`` copies of the running sums (P_l, Σz, Σkz) of ``nb`` columns."""
    return np.zeros((ntaps, nlag, nb)), np.zeros((nlag, nb)), np.zeros((nlag, nb))


@numba.njit(cache=True, nogil=True)
def _grid_block(u, b0, nb, filtered, filt, rring, fit, sums, sse, means):  # pragma: no cover - compiled
    """Score columns b0..b0+nb-1 of ``u`` into rows of ``sse``: one pass over time, then one solve per column
    and dead time (``rring``: rows of the all-pole part's ring).

    The steps of the pass over time are inner functions, which numba inlines: a compiled function called with
    array arguments costs two atomic reference-count updates per array and call, more than one sample's work
    for a single column. Each step works one stage at a time over the block's columns (branch-free inner
    loops) and indexes rows rather than taking row views (a view costs the same updates).
    """
    y, w0, w1, delays, ntaps, trend, _, _ = fit
    alpha, p, gain, start, rmask, integ, dt, highpass, lam, frac = filt
    T = u.shape[0]
    dmin, dmax = delays.min(), delays.max()
    nlag = dmax - dmin + ntaps
    ring, mask = _ring(dmax + ntaps + _TILE)   # the tile of samples whose cross terms are pending, and its lags
    lo0 = w0 - dmax - (ntaps - 1)   # first index of the run of running sums kept near w0
    hi0 = w1 - dmax - (ntaps - 1)   # ... and near w1
    mean = np.zeros(nb) if filtered else means[b0:b0 + nb]
    Z = np.zeros((ring, nb))              # the last `ring` values of z
    R = np.zeros((rring, nb))             # the last values of the all-pole filter's output
    acc = np.zeros(nb)                    # integrator
    v0 = np.zeros(nb)                     # prefilter: its input at k = 0 (it starts at rest there)
    hstate = np.zeros(nb)                 # prefilter: transposed direct-form state
    hprev = np.zeros(nb)                  # prefiltered value at k - 1 (fractional delay)
    P = np.zeros((ntaps, nb))             # running sums P_l(k) = sum_{i<k} z_i z_{i-l}
    P1 = np.zeros(nb)                     # sum_{i<k} z_i
    PK = np.zeros(nb)                     # sum_{i<k} i z_i
    loP, loP1, loPK = _kept_run(ntaps, nlag, nb)
    hiP, hiP1, hiPK = _kept_run(ntaps, nlag, nb)
    X = np.zeros((nlag, nb))              # X[i] = sum_k z_{k - dmin - i} y_k

    def all_pole(k, kz):
        """Unit DC gain, strictly causal; at rest at the first input."""
        kr = k & rmask
        if k < start:
            for j in range(nb):
                R[kr, j] = u[0, b0 + j] - mean[j]
        elif p == 1:   # one pole (every first-order hypothesis): the same two steps, in one loop
            k1 = (k - 1) & rmask
            a1 = alpha[1]
            for j in range(nb):
                r = gain * (u[k - 1, b0 + j] - mean[j])
                r -= a1 * R[k1, j]
                R[kr, j] = r
                Z[kz, j] = r
            return
        else:
            for j in range(nb):
                R[kr, j] = gain * (u[k - 1, b0 + j] - mean[j])
            for i in range(1, p + 1):
                ki = (k - i) & rmask
                ai = alpha[i]
                for j in range(nb):
                    R[kr, j] -= ai * R[ki, j]
        for j in range(nb):
            Z[kz, j] = R[kr, j]

    def integrate(kz):
        for j in range(nb):
            acc[j] += dt * Z[kz, j]
            Z[kz, j] = acc[j]

    def prefilter(k, kz):
        """(1 - q^-1)/(1 - lam q^-1) of z - z_0, transposed direct form (as scipy's lfilter)."""
        if k == 0:
            for j in range(nb):
                v0[j] = Z[kz, j]
        for j in range(nb):
            x = Z[kz, j] - v0[j]
            h = x + hstate[j]
            hstate[j] = -x + lam * h
            Z[kz, j] = h

    def fractional_delay(k, kz):
        for j in range(nb):
            h = Z[kz, j]
            if k > 0:
                Z[kz, j] = (1.0 - frac) * h + frac * hprev[j]
            hprev[j] = h

    def add_running_sums(k, kz):
        for j in range(nb):
            P1[j] += Z[kz, j]
            PK[j] += k * Z[kz, j]
        for tap in range(min(ntaps, k + 1)):
            kt = (k - tap) & mask
            for j in range(nb):
                P[tap, j] += Z[kz, j] * Z[kt, j]

    def add_cross_terms(k0, k1):
        """Samples k0..k1, lag outermost: one row of X stays in the first-level cache while the tile's rows of
        the ring stream past (same summation order as sample by sample)."""
        if nb == 1:  # one column: no inner loop to set up per (lag, sample)
            for kk in range(k0, k1 + 1):
                yk = y[kk]
                for i in range(nlag):
                    X[i, 0] += Z[(kk - dmin - i) & mask, 0] * yk
        else:
            for i in range(nlag):
                for kk in range(k0, k1 + 1):
                    yk = y[kk]
                    ki = (kk - dmin - i) & mask
                    for j in range(nb):
                        X[i, j] += Z[ki, j] * yk

    def add_cross_tile(k0):
        """``add_cross_terms(k0, k0 + 7)`` of a whole tile of several columns: each X[i, j] takes the tile's
        eight products in a register, added in sample order as above — the same sums, with X read and written
        once per tile instead of once per sample (the loop over columns vectorises; a lag of 64 columns costs
        about 0.65 of the sample-by-sample loop)."""
        y0, y1, y2, y3 = y[k0], y[k0 + 1], y[k0 + 2], y[k0 + 3]
        y4, y5, y6, y7 = y[k0 + 4], y[k0 + 5], y[k0 + 6], y[k0 + 7]
        for i in range(nlag):
            b = k0 - dmin - i
            r0, r1, r2, r3 = b & mask, (b + 1) & mask, (b + 2) & mask, (b + 3) & mask
            r4, r5, r6, r7 = (b + 4) & mask, (b + 5) & mask, (b + 6) & mask, (b + 7) & mask
            for j in range(nb):
                s = X[i, j]
                s += Z[r0, j] * y0
                s += Z[r1, j] * y1
                s += Z[r2, j] * y2
                s += Z[r3, j] * y3
                s += Z[r4, j] * y4
                s += Z[r5, j] * y5
                s += Z[r6, j] * y6
                s += Z[r7, j] * y7
                X[i, j] = s

    tile0 = w0                            # first sample whose cross terms are not yet in X
    for k in range(w1 + 1):   # samples after the window are never used (only the mean reads all T)
        # Keep the running sums (over indices < k) where the Gram entries will need them.
        if lo0 <= k < lo0 + nlag:
            _keep(k - lo0, P, P1, PK, loP, loP1, loPK)
        if hi0 <= k < hi0 + nlag:
            _keep(k - hi0, P, P1, PK, hiP, hiP1, hiPK)
        if k == w1:
            break
        kz = k & mask
        if filtered:
            for j in range(nb):
                Z[kz, j] = u[k, b0 + j]
        else:
            all_pole(k, kz)
            if integ:
                integrate(kz)
            if highpass:
                prefilter(k, kz)
            if frac > 0.0:
                fractional_delay(k, kz)
        add_running_sums(k, kz)
        if w0 <= k < w1 and (k - tile0 + 1 == _TILE or k == w1 - 1):
            if nb > 1 and k - tile0 + 1 == _TILE:
                add_cross_tile(tile0)
            else:
                add_cross_terms(tile0, k)
            tile0 = k + 1
    q = ntaps + 1 + trend
    # The columns' systems (one per dead time) solved side by side, at least _SYSTEMS at a time where a column
    # has fewer dead times (see _solve_sses).
    nd = delays.shape[0]
    per = max(1, _SYSTEMS // nd)
    G = np.zeros((q, q, per * nd))
    r = np.zeros((q, per * nd))
    room = _solve_room(q, per * nd)
    out = np.empty(per * nd)
    lo, hi = (loP, loP1, loPK), (hiP, hiP1, hiPK)
    _, _, _, _, _, _, sign, held = fit
    for j0 in range(0, nb, per):
        jn = min(per, nb - j0)
        for jj in range(jn):
            _column_systems(j0 + jj, lo, hi, X, sums, fit, T, dmin, dmax, G, r, jj * nd)
        done = out[:jn * nd]
        _solve_sses(G, r, sums[0], q, ntaps, sign, held, room, done)
        for jj in range(jn):
            for di in range(nd):
                sse[b0 + j0 + jj, di] = done[jj * nd + di]


@numba.njit(cache=True, nogil=True)
def _grid_columns(u, c_lo, c_hi, filtered, stages, fit, sse, mean):  # pragma: no cover - compiled
    """Fill rows c_lo..c_hi-1 of ``sse`` (n, nd), :data:`_BLOCK` columns of ``u`` (T, n; time-major, columns
    innermost) at a time. ``filtered``: ``u`` already holds the regressor source z; otherwise the filter
    ``stages`` ``(alpha, integ, dt, highpass, lam, frac)`` make it from ``u`` less its column means ``mean`` (n,)
    (see :func:`grid_sse`). ``fit`` is ``(y, w0, w1, delays, ntaps, trend, sign, held)``."""
    T = u.shape[0]
    alpha, integ, dt, highpass, lam, frac = stages
    p, gain, start, rring, rmask = _filter_setup(alpha, T)
    filt = (alpha, p, gain, start, rmask, integ, dt, highpass, lam, frac)
    sums = _window_sums(fit[0], fit[1], fit[2], T)
    for b0 in range(c_lo, c_hi, _BLOCK):
        _grid_block(u, b0, min(_BLOCK, c_hi - b0), filtered, filt, rring, fit, sums, sse, mean)


@numba.njit(cache=True, nogil=True)
def _column_sse(u, mean, alpha, integ, dt, highpass, lam, frac, y, w0, w1, m, ntaps, trend, sign):  # pragma: no cover
    """Compiled body of :func:`column_sse` (``mean``: ``u``'s, :func:`column_mean`)."""
    T = u.shape[0]
    q = ntaps + 1 + trend
    p, gain, start, rring, rmask = _filter_setup(alpha, T)
    ring, mask = _ring(m + ntaps + 1)
    Z = np.zeros(ring)
    R = np.zeros(rring)
    acc = v0 = hstate = hprev = last = last2 = 0.0
    a1 = alpha[1] if p >= 1 else 0.0
    a2 = alpha[2] if p >= 2 else 0.0
    G = np.zeros((q, q, 1))
    g02 = g12 = g22 = r2 = 0.0
    r = np.zeros((q, 1))
    x = np.zeros(q)
    yy = g00 = g01 = g11 = r0 = r1 = 0.0
    for k in range(w1):
        if k < start:
            s = u[0] - mean
        elif p == 1:
            # One or two poles: the last outputs from registers (the same operations in the same order). Read
            # back from R, the recursion waited on the store at every sample; it is what bounds this loop.
            s = gain * (u[k - 1] - mean)
            s -= a1 * last
        elif p == 2:
            s = gain * (u[k - 1] - mean)
            s -= a1 * last
            s -= a2 * last2
        else:
            s = gain * (u[k - 1] - mean)
            for i in range(1, p + 1):
                s -= alpha[i] * R[(k - i) & rmask]
        R[k & rmask] = s
        last2 = last
        last = s
        if integ:
            acc += dt * s
            s = acc
        if highpass:
            if k == 0:
                v0 = s
            xk = s - v0
            h = xk + hstate
            hstate = -xk + lam * h
            s = h
        if frac > 0.0:
            h = s
            if k > 0:
                s = (1.0 - frac) * h + frac * hprev
            hprev = h
        Z[k & mask] = s
        if k >= w0 and q == 2:
            # One tap and the offset (a first-order plant, the common case): the same sums in registers. The
            # offset's regressor is 1, and x·1 is x exactly, so these are the general branch's numbers.
            x0 = s if m == 0 else Z[(k - m) & mask]   # (with no dead time, the value just stored)
            yk = y[k]
            yy += yk * yk
            g00 += x0 * x0
            g01 += x0
            g11 += 1.0
            r0 += x0 * yk
            r1 += yk
        elif k >= w0 and ntaps == 2 and not trend:
            # Two taps and the offset (a second-order plant or a fractional dead time): the same, in registers.
            x0 = s if m == 0 else Z[(k - m) & mask]
            x1 = Z[(k - m - 1) & mask]
            yk = y[k]
            yy += yk * yk
            r0 += x0 * yk
            g00 += x0 * x0
            g01 += x0 * x1
            g02 += x0
            r1 += x1 * yk
            g11 += x1 * x1
            g12 += x1
            r2 += yk
            g22 += 1.0
        elif k >= w0:
            for i in range(ntaps):
                x[i] = Z[(k - m - i) & mask]
            x[ntaps] = 1.0
            if trend:
                x[ntaps + 1] = k / T
            yk = y[k]
            yy += yk * yk
            for i in range(q):
                r[i, 0] += x[i] * yk
                for jj in range(i, q):
                    G[i, jj, 0] += x[i] * x[jj]
    if q == 2:
        G[0, 0, 0], G[0, 1, 0], G[1, 1, 0], r[0, 0], r[1, 0] = g00, g01, g11, r0, r1
    elif ntaps == 2 and not trend:
        G[0, 0, 0], G[0, 1, 0], G[0, 2, 0], r[0, 0] = g00, g01, g02, r0
        G[1, 1, 0], G[1, 2, 0], r[1, 0] = g11, g12, r1
        G[2, 2, 0], r[2, 0] = g22, r2
    out = np.zeros(1)
    _solve_sses(G, r, yy, q, ntaps, sign, np.nan, _solve_room(q, 1), out)
    return out[0]


def column_sse(u, alpha, integ, dt, lam, frac, y, w0, w1, m, ntaps, trend, sign=0, mean=None) -> float:
    """SSE of the fit for one input column ``u`` (T,) and one dead time of ``m`` whole samples plus ``frac``.

    The arguments are :func:`grid_sse`'s for a single column and a single delay; this scalar version of the same
    pass is what a polish evaluates thousands of times (the block kernel's per-sample loop set-up, amortised
    over a block of columns, would dominate for one). The Gram entries are summed directly over the window.
    ``sign``: the gain's required sign (see :func:`grid_sse`). ``mean``: ``u``'s mean (:func:`column_mean`),
    which a polish computes once for all its evaluations of one column.
    """
    u = kernel_array(u).reshape(-1)
    return float(_column_sse(u, _column_mean(u) if mean is None else float(mean), kernel_array(alpha), bool(integ),
                             float(dt), lam is not None, float(lam or 0.0), float(frac), kernel_array(y), int(w0),
                             int(w1), int(m), int(ntaps), int(trend), float(sign)))


@numba.njit(cache=True, nogil=True)
def _column_mean(u):  # pragma: no cover - compiled
    """Mean of ``u`` (T,), summed in time order."""
    mean = 0.0
    for k in range(u.shape[0]):
        mean += u[k]
    return mean / u.shape[0]


def column_mean(u: np.ndarray) -> float:
    """The mean :func:`column_sse` subtracts from its input column ``u`` (T,) before filtering."""
    return float(_column_mean(kernel_array(u).reshape(-1)))


def grid_sse(u, y, w0, w1, delays, ntaps, trend, sse, *, filtered=False, alpha=None, integ=False, dt=1.0,
             lam=None, frac=0.0, sign=0, gain=None, means=None) -> None:
    """Fill ``sse`` (n, nd) for every column of ``u`` (T, n) and every dead time of ``delays``, in place.

    ``filtered``: ``u`` is already the regressor source z. Otherwise z is made from each column minus its mean
    by the all-pole filter ``alpha`` (unit DC gain, one sample of delay), an integrator (``integ``, scaled by
    ``dt``), the high-pass prefilter of pole ``lam`` (None: none) and a fractional delay ``frac`` (0 ≤ f < 1).
    ``sign`` (+1, −1; 0: free): the sign the gain (sum of the taps) must have; a column whose free fit has the
    other sign scores the SSE of the best fit with gain 0. ``gain`` (None: free): the gain held, every column
    scored at it (see :func:`_solve_sses`). ``means``: the column means of ``u`` (:func:`column_means`) when known.
    """
    u = kernel_array(u)
    means = (np.zeros(u.shape[1]) if filtered else column_means(u)) if means is None else kernel_array(means)
    alpha = np.ones(1) if alpha is None else kernel_array(alpha)
    stages = (alpha, bool(integ), float(dt), lam is not None, float(lam or 0.0), float(frac))
    fit = (kernel_array(y), int(w0), int(w1), kernel_array(delays, np.int64), int(ntaps), int(trend), float(sign),
           np.nan if gain is None else float(gain))
    n = u.shape[1]
    if n <= _GROUP:
        _score_columns(u, bool(filtered), stages, fit, sse, means)
        return
    for a in range(0, n, _GROUP):
        _score_columns(np.ascontiguousarray(u[:, a:a + _GROUP]), bool(filtered), stages, fit, sse[a:a + _GROUP],
                       np.ascontiguousarray(means[a:a + _GROUP]))


def _score_columns(u: np.ndarray, filtered: bool, stages: tuple, fit: tuple, sse: np.ndarray, means: np.ndarray
                   ) -> None:
    """:func:`grid_sse` of the columns of ``u`` (C-contiguous), split over the worker threads."""
    n = u.shape[1]
    workers = workers_for(n)
    # Whole blocks per worker, as even as the block size allows.
    cuts = [min(n, _BLOCK * round(n * w / workers / _BLOCK)) for w in range(workers + 1)]
    cuts[-1] = n
    run_split(lambda a, b: _grid_columns(u, a, b, filtered, stages, fit, sse, means), cuts)


@numba.njit(cache=True, nogil=True)
def normal_equations(X, y):  # pragma: no cover - compiled
    """``(XᵀX, Xᵀy)`` of a tall, skinny least-squares problem, single-threaded.

    Why not ``X.T @ X``: numpy hands that to a multi-threaded BLAS, whose threads then compete with the
    compiled kernels' threads for the same cores; at 10⁴–10⁵ samples that contention doubled the
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


@numba.njit(cache=True, nogil=True)
def normal_equations_rows(X, y, rows, G, b):  # pragma: no cover - compiled
    """:func:`normal_equations` of ``X`` (T, q) and ``y`` where only the first ``rows`` columns of ``X`` are new:
    ``G`` (q, q) and ``b`` (q,) hold the other columns' entries (from an earlier call on the same columns) and are
    completed in place. Each entry is its own sum over the samples in time order, the same products as
    :func:`normal_equations`, so the result is the same to the bit; a least-squares fit whose other columns (an
    offset, a ramp, extra regressors) stay the same over many fits (a polish) recomputes only its taps' rows."""
    T, q = X.shape
    for i in range(rows):   # row by row: each entry still sums its products over the samples in time order
        for j in range(i, q):
            G[i, j] = 0.0
        bi = 0.0
        for k in range(T):
            xi = X[k, i]
            bi += xi * y[k]
            for j in range(i, q):
                G[i, j] += xi * X[k, j]
        b[i] = bi
    for i in range(1, q):
        for j in range(i):
            G[i, j] = G[j, i]
