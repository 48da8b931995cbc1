r"""The linear part of a Hammerstein model, fitted by output error for many input candidates at once.

Model
-----
The plant input :math:`u_k` (valve flow, %, one column per candidate valve) drives

.. math::
   \hat y_k = \sum_{j=0}^{p-1} b_j\, z_{k-d-j} + c_0 + c_1\,\frac{k - k_0}{T}\;[\text{integrating only}],
   \qquad z = \frac{q^{-1}\,g}{A_s(q)\,(1 - q^{-1})^{i}}\, u ,

with :math:`A_s(q) = \prod_l (1 - e^{-\Delta t/\tau_l} q^{-1})` (the stable poles, fixed for one fit),
:math:`i \in \{0, 1\}` an integrator (scaled by :math:`\Delta t`, so the gain is per second),
:math:`g = A_s(1)` (unit DC gain of the stable part), :math:`p = \max(1, \text{order})` numerator taps
and an integer dead time of :math:`d` samples. Every exact zero-order-hold discretisation of a proper
:math:`K e^{-\theta s}/\mathrm{den}(s)` with :math:`\theta = d\Delta t` is of this form (Åström & Wittenmark,
*Computer-Controlled Systems*, 3rd ed., §2.3), so a correct structure can replay a noise-free recording
exactly. The trend term of an integrating plant absorbs the unknown operating-point flow :math:`u_0`
(:math:`\sum (u - u_0) = \sum u - k u_0`); the constant absorbs :math:`\mathrm{pv}_0` and the integrator's
initial state.

Why output error, fitted by linear least squares
-------------------------------------------------
With the poles fixed, :math:`\hat y` is linear in :math:`(b, c)`, and the regressors are filtered *inputs*
only, never past outputs. The residual is then the measurement noise itself, which is white and, in closed
loop, independent of the past inputs that form the regressors (OP at sample k depends on noise up to k,
while :math:`\hat y_k` uses flow up to :math:`k - d - 1`). Equation-error ARX, whose regressors contain
noisy past PV, is biased in that setting; this least-squares problem is not (direct prediction-error
identification with the correct noise model :math:`H = 1`; Ljung, *System Identification*, 2nd ed., §13.4).
The poles and a fractional dead time are refined afterwards by :func:`polish` (variable projection:
Nelder–Mead on the poles, least squares inside).

Vectorised search
-----------------
:func:`delay_grid_sse` returns the residual sum of squares for every candidate column and every dead
time of a grid in one compiled, parallel call (normal equations of at most five unknowns, solved by
Cholesky per column and delay). The first sample scored, ``w0``, must leave room for the longest delay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numba
import numpy as np

from valve_emulator.diagnosis.fit.cost import log_sse
from valve_emulator.diagnosis.fit.linear_kernels import (
    RIDGE,
    _column_sse,
    column_mean,
    column_sse,
    grid_sse,
    normal_equations,
    normal_equations_rows,
)
from valve_emulator.diagnosis.fit.simplex import nelder_mead
from valve_emulator.physics._arrays import kernel_array

__all__ = [
    "PRIOR_WIDTH",
    "prior_term",
    "LinearStructure",
    "LinearFit",
    "highpass",
    "iir_filter",
    "filter_inputs",
    "input_grid_sse",
    "delay_grid_sse",
    "split_delay",
    "delayed_regressors",
    "fit_one",
    "fit_filtered",
    "on_pv",
    "OneColumn",
    "sse_one",
    "polish",
]

#: Width (1 σ, natural log) of the prior on re-fitted time constants: the nominal trusted to within 25 %.
PRIOR_WIDTH = float(np.log(1.25))


@dataclass(frozen=True)
class LinearStructure:
    """Denominator of the linear part and its dead time.

    Attributes
    ----------
    taus : time constants (s, > 0) of the real stable poles; refined by :func:`polish`.
    integrating : one pole at s = 0.
    fixed_poles : further continuous-time poles (complex pairs of a nominal model), kept as given.
    delay : dead time θ (s, >= 0); fractional multiples of ``dt`` are allowed.
    taus_held : the time constants are the nominal model's, held (not refined by :func:`polish`, not counted
        by BIC).
    gain : a steady-state gain held at the nominal model's (sum of the taps, in the fit's units: scaled PV per
        % flow, per second for an integrator), or None when the taps are fitted freely.
    sign : the sign the gain must have (+1 or −1), 0 when it is free. A plant identified from a closed loop
        takes it from the controller's action (:mod:`~valve_emulator.diagnosis.fit.closed_loop`): a fit whose
        free gain has the other sign is replaced by the best fit with gain 0 (the constrained least-squares
        optimum), so the controller run backwards is never a fit.
    min_tau : the shortest time constant :func:`polish` may reach (s); 0 for ``dt/20``. An identified plant
        keeps its time constants at least one sample: a faster pole is what fits the controller's inverse.
    """

    taus: tuple[float, ...] = ()
    integrating: bool = False
    fixed_poles: tuple[complex, ...] = ()
    delay: float = 0.0
    taus_held: bool = False
    gain: float | None = None
    sign: int = 0
    min_tau: float = 0.0

    @property
    def order(self) -> int:
        return len(self.taus) + len(self.fixed_poles) + int(self.integrating)

    @property
    def ntaps(self) -> int:
        return max(1, self.order)

    def n_params(self) -> int:
        """Parameters of the linear part counted by BIC: taps, offset, trend, fitted time constants (a held
        gain removes one tap, held time constants are not counted)."""
        taus = 0 if self.taus_held else len(self.taus)
        return self.ntaps - int(self.gain is not None) + 1 + int(self.integrating) + taus

    def denominator(self, dt: float) -> np.ndarray:
        """Coefficients ``[1, α1, …]`` of the stable part :math:`A_s(q)` in powers of :math:`q^{-1}`."""
        if not self.fixed_poles:
            return _real_denominator(self.taus, dt)
        real = [np.exp(-dt / t) for t in self.taus]
        return np.real(np.poly(real + [np.exp(p * dt) for p in self.fixed_poles]))

    def describe(self) -> str:
        parts = [f"1/({t:.3g}s+1)" for t in self.taus]
        if self.fixed_poles:
            parts.append(f"{len(self.fixed_poles)} fixed poles")
        if self.integrating:
            parts.insert(0, "1/s")
        return ("·".join(parts) or "gain") + f"·e^(-{self.delay:.3g}s)"


def _real_denominator(taus: tuple[float, ...], dt: float) -> np.ndarray:
    """:meth:`LinearStructure.denominator` of real time constants ``taus`` only (no fixed poles)."""
    return _real_poly([np.exp(-dt / t) for t in taus])


def _real_poly(roots: list) -> np.ndarray:
    """``np.real(np.poly(roots))`` for real roots, bit for bit: the same products and two-term sums of its
    convolutions, without numpy's overhead per call (a polish asks for thousands of denominators)."""
    a = [1.0]
    for r in roots:
        q = -r
        a = [1.0, *(a[k] + a[k - 1] * q for k in range(1, len(a))), a[-1] * q]
    return np.array(a, dtype=float)


@dataclass(frozen=True)
class LinearFit:
    """A fitted linear part: structure, numerator taps and offsets, and its scores on the fit window."""

    structure: LinearStructure
    taps: np.ndarray = field(repr=False)
    offset: float
    trend: float
    sse: float
    n: int

    @property
    def gain(self) -> float:
        """Steady-state gain (PV units per % flow; per second for an integrating plant)."""
        return float(np.sum(self.taps))

    def predict(self, u: np.ndarray, dt: float, *, level: float | None = None,
                record_length: int | None = None) -> np.ndarray:
        """Free-run PV for the input ``u`` (T,) (same conventions as the fit).

        The fit removed the input's mean and scaled the trend regressor by the record's length; on the record
        itself both defaults hold. For another input pass the fitted record's ``level`` (its mean input) and
        ``record_length`` so that the offset and trend keep their meaning.
        """
        z = filter_inputs(u, self.structure, dt, mean=level)
        x = delayed_regressors(z, self.structure.delay / dt, self.structure.ntaps)
        T = u.shape[0]
        return x @ self.taps + self.offset + self.trend * (np.arange(T) / (record_length or T))


@numba.njit(cache=True, nogil=True)
def _transposed_direct_form(b, a, x, z):  # pragma: no cover - compiled
    """``b/a`` (same lengths, ``a[0]`` = 1) along axis 0 of ``x`` (T, n), state ``z`` (len - 1, n) updated in
    place: the loop of scipy's ``lfilter`` (``lfilter.c.src``), operation for operation."""
    y = np.empty_like(x)
    m = b.size
    for k in range(x.shape[0]):
        for j in range(x.shape[1]):
            xn = x[k, j]
            if m == 1:
                y[k, j] = xn * b[0]
                continue
            yn = z[0, j] + b[0] * xn
            for i in range(m - 2):
                z[i, j] = z[i + 1, j] + xn * b[i + 1] - yn * a[i + 1]
            z[m - 2, j] = xn * b[m - 1] - yn * a[m - 1]
            y[k, j] = yn
    return y


def iir_filter(b, a, x: np.ndarray, zi: np.ndarray | None = None) -> np.ndarray:
    """``scipy.signal.lfilter(b, a, x, axis=0, zi=zi)``'s output (its first element when ``zi`` is given), the
    same bits, for float ``x`` (T,) or (T, n) and ``zi`` (max(len(a), len(b)) - 1, n).

    The same arithmetic as scipy's (coefficients padded to one length and divided by ``a[0]``, the transposed
    direct form II loop), compiled here so that the diagnosis does not import :mod:`scipy.signal` (with the
    :mod:`scipy.stats` it pulls in, ~0.6 s of a first run) for this one filter."""
    b, a = np.atleast_1d(np.asarray(b, dtype=float)), np.atleast_1d(np.asarray(a, dtype=float))
    m = max(b.size, a.size)
    # Padding to one length and dividing by a[0]; skipped where they change nothing (coefficients of one length
    # already, a[0] = 1: x / 1.0 is x to the bit), as for every filter of the diagnosis' polishes.
    if b.size < m:
        b = np.concatenate([b, np.zeros(m - b.size)])
    if a.size < m:
        a = np.concatenate([a, np.zeros(m - a.size)])
    if a[0] != 1.0:
        b, a = b / a[0], a / a[0]
    x = np.asarray(x, dtype=float)
    x2 = kernel_array(x[:, None] if x.ndim == 1 else x)
    z = np.zeros((m - 1, x2.shape[1])) if zi is None else kernel_array(np.array(zi, dtype=float)).reshape(m - 1, -1)
    return _transposed_direct_form(b, a, x2, z).reshape(x.shape)


def filter_inputs(u: np.ndarray, structure: LinearStructure, dt: float, *, mean: float | None = None
                  ) -> np.ndarray:
    """The regressor source :math:`z` (see the module docstring), time along axis 0: (T,) or (T, n).

    ``mean`` is the input level removed before filtering (default: each column's own mean). The filter starts
    at rest for the first input: :math:`z_k = u_0` until the filter's order is reached.
    """
    u = np.asarray(u, dtype=np.float64)
    u2 = u[:, None] if u.ndim == 1 else u
    # A constant per column changes z by a constant (or, integrating, by a ramp) that the offset and
    # trend regressors absorb; removing the mean keeps the cumulative sums of an integrator small.
    out = _filter_centred(u2 - (u2.mean(axis=0) if mean is None else float(mean)), structure, dt)
    return out[:, 0] if u.ndim == 1 else out


def _filter_centred(x: np.ndarray, structure: LinearStructure, dt: float) -> np.ndarray:
    """:func:`filter_inputs` of the input less its level, ``x`` (T, n): a polish that filters one input for many
    structures removes the level once."""
    alpha = structure.denominator(dt)
    p = alpha.size - 1
    T = x.shape[0]
    start = min(max(p, 1), T)
    out = np.empty_like(x)
    out[:start] = x[0]
    if start < T:
        # z_k = g u_{k-1} - sum_i alpha_i z_{k-i} from k = start, the earlier outputs all u_0: the filter's
        # state for those past outputs (scipy.signal.lfiltic's formula, one column at a time at once).
        zi = -np.cumsum(alpha[:0:-1])[::-1][:, None] * x[0] if p else None
        b = [float(np.sum(alpha))]
        seg = x[start - 1:T - 1]
        out[start:] = iir_filter(b, alpha, seg, zi)
    if structure.integrating:
        out = np.cumsum(dt * out, axis=0)
    return out


def input_grid_sse(u: np.ndarray, y: np.ndarray, window: tuple[int, int], delays: np.ndarray,
                   structure: LinearStructure, dt: float, *, prefilter: float | None = None,
                   frac: float = 0.0, means: np.ndarray | None = None) -> np.ndarray:
    """Residual sum of squares for every column of the plant input ``u`` (T, n) and every dead time.

    The same numbers as :func:`delay_grid_sse` of :func:`filter_inputs` (then :func:`highpass` with
    ``prefilter``, then a delay by the fraction ``frac`` of a sample), in one compiled pass per column that
    never stores the filtered inputs. ``y`` is in the cost domain (prefiltered with ``prefilter``). ``means``:
    ``u``'s column means (:func:`~valve_emulator.diagnosis.fit.linear_kernels.column_means`), when ``u`` is
    scored for several structures.

    A structure that holds its gain (``structure.gain``) is scored at that gain, as :func:`fit_one` fits it: the
    free fit's SSE plus what holding the taps' sum costs (an equality-constrained least-squares problem,
    :func:`~valve_emulator.diagnosis.fit.linear_kernels.grid_sse`), in the same pass. Fitted freely, a grid
    "at the held gain" chose the row that suits the gain the data prefer and only the polish after it held the
    gain: refined again around a nominal gain (:mod:`~valve_emulator.diagnosis.explain.prior`), a late valve
    stayed at the band that suited the moved gain (the independent ``late_onset`` loops with their model, draw
    10 of the onset property: S 2.38 % for 4.33, the grid's best row at the held gain 2.25 %).
    """
    u = u[:, None] if u.ndim == 1 else u
    delays = np.asarray(delays, dtype=np.int64)
    w0, w1 = _check_window(window, delays, structure)
    trend = int(structure.integrating and prefilter is None)
    sse = np.empty((u.shape[1], delays.size))
    grid_sse(u, y, w0, w1, delays, structure.ntaps, trend, sse, alpha=structure.denominator(dt),
             integ=structure.integrating, dt=dt, lam=prefilter, frac=frac, sign=structure.sign, gain=structure.gain,
             means=means)
    return sse


def _check_window(window: tuple[int, int], delays: np.ndarray, structure: LinearStructure) -> tuple[int, int]:
    w0, w1 = int(window[0]), int(window[1])
    if delays.size == 0:
        raise ValueError("no dead times to score")
    if w0 < int(delays.max()) + structure.ntaps - 1:
        raise ValueError(f"window start {w0} leaves no room for delay {int(delays.max())} samples")
    return w0, w1


def delay_grid_sse(z: np.ndarray, y: np.ndarray, window: tuple[int, int], delays: np.ndarray,
                   structure: LinearStructure, *, prefiltered: bool = False) -> np.ndarray:
    """Residual sum of squares of the least-squares fit for every column of ``z`` and every delay.

    Parameters
    ----------
    z : (T, n) filtered inputs from :func:`filter_inputs` (time along axis 0).
    y : (T,) measured PV (centre and scale it for conditioning; the constant regressor absorbs the mean).
    window : ``(w0, w1)`` samples scored; ``w0 >= max(delays) + ntaps - 1``.
    delays : integer dead times in samples.
    structure : supplies ``ntaps`` and ``integrating`` (the trend regressor).
    prefiltered : ``z`` and ``y`` went through :func:`highpass`: no trend regressor.

    Returns
    -------
    sse : (n, len(delays)).
    """
    delays = np.asarray(delays, dtype=np.int64)
    w0, w1 = _check_window(window, delays, structure)
    trend = int(structure.integrating and not prefiltered)
    sse = np.empty((z.shape[1], delays.size))
    grid_sse(z, y, w0, w1, delays, structure.ntaps, trend, sse, filtered=True, sign=structure.sign)
    return sse


def split_delay(delay_samples: float) -> tuple[int, float]:
    """A dead time in samples as whole samples ``m`` and the fraction ``f`` of one more (0 ≤ f < 1)."""
    m = math.floor(delay_samples + 1e-9)
    return m, max(0.0, delay_samples - m)


def _shift(z: np.ndarray, s: int, w0: int = 0, w1: int | None = None) -> np.ndarray:
    """``z_{k-s}`` for the rows ``w0 <= k < w1`` (default: the whole record), holding the first value before the
    record starts; a view of ``z`` where nothing is held."""
    w1 = z.shape[0] if w1 is None else w1
    if s <= 0:
        return z[w0:w1]
    if w0 >= s:
        return z[w0 - s:w1 - s]
    held = min(s - w0, w1 - w0)
    out = np.empty((w1 - w0,) + z.shape[1:], dtype=z.dtype)
    out[:held] = z[0]
    out[held:] = z[w0 + held - s:w1 - s]
    return out


def delayed_regressors(z: np.ndarray, delay_samples: float, ntaps: int, window: tuple[int, int] | None = None, *,
                       out: np.ndarray | None = None) -> np.ndarray:
    """Columns ``z_{k-d-j}`` for a possibly fractional delay ``d = m + f`` (linear interpolation), of the rows
    ``window`` = ``(w0, w1)`` (default: the whole record), into ``out`` (rows, ntaps, …) when given.

    Interpolating the filtered input between samples is the first-order (in Δt/τ) form of the exact
    fractional-delay ZOH of Åström & Wittenmark; it is exact for the integer delays the grid uses. A window's
    rows are the whole record's rows there, the same numbers (the same shifts, the same interpolation of each
    sample), without shifting the whole record.
    """
    w0, w1 = (0, z.shape[0]) if window is None else window
    m, f = split_delay(delay_samples)
    if out is None:
        out = np.empty((w1 - w0, ntaps) + z.shape[1:], dtype=np.result_type(z.dtype, np.float64))
    for j in range(ntaps):
        col = _shift(z, m + j, w0, w1)
        if f > 0.0:
            col = (1.0 - f) * col + f * _shift(z, m + j + 1, w0, w1)
        out[:, j] = col
    return out


def highpass(x: np.ndarray, lam: float) -> np.ndarray:
    r"""Prefilter :math:`L(q) = (1 - q^{-1})/(1 - \lambda q^{-1})` along the time axis (0), at rest at x[0].

    Why, for integrating plants: fitting :math:`L\,\mathrm{PV}` on :math:`L z` is the same linear model
    (L commutes with the plant; Ljung, *System Identification*, 2nd ed., §14.4, prefiltering as frequency
    weighting) but changes what a slip-timing error of a candidate valve costs. In the PV itself an
    integrator turns every such error into a permanent offset, so the cost over (S, J) is needle-sharp and
    rough (an island of a few hundredths of a percent); on first differences (λ = 0) an error costs one
    sample and the measurement noise, amplified, hides J. With :math:`\lambda = 1 - 1/T_c` an error costs
    for about :math:`T_c` samples: smooth enough to search, sharp enough to separate stiction from
    deadband. The trend regressor of an integrating plant becomes (after a transient) a constant, and the
    constant a decaying transient, so a prefiltered fit uses taps plus one constant (no trend).
    """
    x = np.asarray(x, dtype=float)
    return iir_filter([1.0, -1.0], [1.0, -float(lam)], x - x[0])  # at rest at the first sample


def fit_one(u: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure,
            dt: float, *, prefilter: float | None = None, extra: np.ndarray | None = None) -> LinearFit:
    """Least-squares fit of the taps and offsets for one input column and a (fractional) delay.

    With ``prefilter`` (λ of :func:`highpass`) the fit is done on prefiltered ``y`` and filtered input (no
    trend regressor); the returned fit then predicts prefiltered PV, so use it for its ``sse`` only.
    ``extra`` (T, m) are further regressors fitted jointly (an additive output term, e.g. a sinusoid); their
    coefficients are not part of the fit's :meth:`~LinearFit.predict`, which stays the linear part's.
    """
    z = filter_inputs(u, structure, dt)
    if prefilter is not None:
        z, y = highpass(z, prefilter), highpass(y, prefilter)
        extra = None if extra is None else highpass(extra, prefilter)
    return fit_filtered(z, y, window, structure, dt, prefiltered=prefilter is not None, extra=extra)


def fit_filtered(z: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure, dt: float, *,
                 prefiltered: bool, extra: np.ndarray | None = None) -> LinearFit:
    """:func:`fit_one` from its filtered input ``z`` (T,) — :func:`filter_inputs` of the input, then
    :func:`highpass` when ``prefiltered`` — and ``y`` and ``extra`` in the same cost domain: the same numbers.

    The filtered input depends on the structure's poles, not on its dead time, and the prefiltered ``y`` and
    ``extra`` on neither, so callers that fit one input or one target many times (a polish with extra
    regressors, an output candidate's grid rows) filter them once."""
    trend = structure.integrating and not prefiltered
    if structure.gain is not None:
        return _fit_held_gain(delayed_regressors(z, structure.delay / dt, structure.ntaps, window), y, window,
                              structure, trend, extra)
    w0, w1 = window
    Xw, yw = _window_design(z, structure.delay / dt, structure.ntaps, window, trend, extra), kernel_array(y[w0:w1])
    G, b = normal_equations(Xw, yw)
    beta = _ridge_solve(G, b, _singular_guard(G.shape[0]))
    nt = structure.ntaps
    if structure.sign * float(np.sum(beta[:nt])) < 0.0:
        # The gain has the sign the controller's action forbids: the constrained optimum has gain 0.
        x = delayed_regressors(z, structure.delay / dt, structure.ntaps, window)
        held = _fit_held_gain(x, y, window, replace(structure, gain=0.0), trend, extra)
        return replace(held, structure=structure)
    res = yw - Xw @ beta
    return LinearFit(structure, beta[:nt].copy(), float(beta[nt]), float(beta[nt + 1]) if trend else 0.0,
                     float(res @ res), w1 - w0)


def _singular_guard(q: int) -> np.ndarray:
    """What :func:`_ridge_solve` adds to a (q, q) G so that an exactly singular one still solves."""
    return 1e-300 * np.eye(q)


def _ridge_solve(G: np.ndarray, b: np.ndarray, guard: np.ndarray) -> np.ndarray:
    """The normal equations ``G β = b`` solved with the relative :data:`RIDGE` on G's diagonal (in place) and
    ``guard`` (:func:`_singular_guard`) added: every least-squares fit of the linear part solves this way."""
    for i in range(G.shape[0]):
        G[i, i] *= 1.0 + RIDGE
    return np.linalg.solve(G + guard, b)


class FixedColumns:
    """:func:`fit_filtered`'s SSE for many filtered inputs against one target ``y`` on one window, with the same
    number of taps, trend and ``extra`` regressors: a polish with extra regressors, where only the filtered input
    changes from one evaluation to the next.

    The columns that do not depend on it (the offset, the ramp, the extra regressors) are laid out once in the
    window's regressor matrix, and their normal equations computed once; each evaluation writes its taps into
    the matrix and computes their rows only (:func:`~valve_emulator.diagnosis.fit.linear_kernels.
    normal_equations_rows`). Every number is :func:`fit_filtered`'s, to the bit. One instance serves one thread.
    """

    def __init__(self, y: np.ndarray, window: tuple[int, int], ntaps: int, trend: bool, extra: np.ndarray | None
                 ) -> None:
        w0, w1 = window
        self.y, self.window, self.ntaps, self.trend, self.extra = y, window, ntaps, trend, extra
        self.Xw = _design(ntaps, trend, extra, y.shape[0], window)
        self.Xw[:, :ntaps] = 0.0   # the taps' columns: each evaluation writes its own
        self.yw = kernel_array(y[w0:w1])
        self.G, self.b = normal_equations(self.Xw, self.yw)   # the fixed columns' entries; the taps' are redone
        q = self.Xw.shape[1]
        self._guard = _singular_guard(q)

    def sse(self, z: np.ndarray, structure: LinearStructure, dt: float) -> float:
        """``fit_filtered(z, y, window, structure, dt, ...).sse`` (``structure``: this number of taps and trend)."""
        nt = self.ntaps
        if structure.gain is not None:
            x = delayed_regressors(z, structure.delay / dt, nt, self.window)
            return _fit_held_gain(x, self.y, self.window, structure, self.trend, self.extra).sse
        Xw, yw = self.Xw, self.yw
        delayed_regressors(z, structure.delay / dt, nt, self.window, out=Xw[:, :nt])   # the window's taps only
        G, b = self.G.copy(), self.b.copy()
        normal_equations_rows(Xw, yw, nt, G, b)
        beta = _ridge_solve(G, b, self._guard)
        if structure.sign * float(np.sum(beta[:nt])) < 0.0:
            x = delayed_regressors(z, structure.delay / dt, nt, self.window)
            return _fit_held_gain(x, self.y, self.window, replace(structure, gain=0.0), self.trend, self.extra).sse
        res = yw - Xw @ beta
        return float(res @ res)


def on_pv(fit: LinearFit, u: np.ndarray, y: np.ndarray, window: tuple[int, int], dt: float) -> LinearFit:
    """A fit made on prefiltered PV carried to PV itself (its offset and trend), for predicting PV.

    The taps are re-fitted with the offsets on PV (:func:`fit_one`) — unless the structure holds the gain's
    sign and that re-fit would break it. On PV an integrating plant's wandering load, which the controller
    answers, weighs more than the valve's moves, and can pull the gain to the sign of the controller's
    inverse; the prefiltered fit, which forgets the load, then keeps its taps and only the offsets are fitted.
    """
    level = fit_one(u, y, window, fit.structure, dt)
    st = fit.structure
    if st.sign == 0 or st.sign * level.gain > 0.0 or st.sign * fit.gain <= 0.0:
        return level
    x = delayed_regressors(filter_inputs(u, st, dt), st.delay / dt, st.ntaps, window)
    X = _design(0, st.integrating, None, u.shape[0], window)
    w0, w1 = window
    rest = y[w0:w1] - x @ fit.taps
    beta, *_ = np.linalg.lstsq(X, rest, rcond=None)
    res = rest - X @ beta
    return LinearFit(st, fit.taps.copy(), float(beta[0]), float(beta[1]) if st.integrating else 0.0,
                     float(res @ res), w1 - w0)


def _window_design(z: np.ndarray, delay_samples: float, ntaps: int, window: tuple[int, int], trend: bool,
                   extra: np.ndarray | None) -> np.ndarray:
    """The least-squares columns of the rows ``window`` (``z`` (T,)): :func:`delayed_regressors`' taps, then
    :func:`_design`'s offset, ramp and ``extra``; C-contiguous, each entry the whole record's number there."""
    X = _design(ntaps, trend, extra, z.shape[0], window)
    delayed_regressors(z, delay_samples, ntaps, window, out=X[:, :ntaps])
    return X


def _design(k: int, trend: bool, extra: np.ndarray | None, T: int, window: tuple[int, int]) -> np.ndarray:
    """The rows ``window`` of the least-squares columns of a record of ``T`` samples, C-contiguous: ``k`` taps
    (left for the caller to fill), an offset, a ramp ``k/T`` over the record when ``trend``, and ``extra``
    ((T,) or (T, m))."""
    w0, w1 = window
    more = None if extra is None else np.asarray(extra, dtype=float).reshape(T, -1)
    X = np.empty((w1 - w0, k + 1 + int(trend) + (0 if more is None else more.shape[1])))
    X[:, k] = 1.0
    if trend:
        X[:, k + 1] = np.arange(w0, w1) / T
    if more is not None:
        X[:, k + 1 + int(trend):] = more[w0:w1]
    return X


def _fit_held_gain(x: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure,
                   trend: bool, extra: np.ndarray | None) -> LinearFit:
    """:func:`fit_one` with the taps' sum held at ``structure.gain``: the first tap is ``g − Σ_{j≥1} b_j``, so
    ``y − g x_0`` is fitted on ``x_j − x_0`` (j ≥ 1), the offsets and ``extra`` by least squares. ``x``: the
    window's rows of :func:`delayed_regressors`."""
    g = float(structure.gain)
    nt = structure.ntaps
    w0, w1 = window
    X = _design(nt - 1, trend, extra, y.shape[0], window)
    X[:, :nt - 1] = x[:, 1:] - x[:, :1]
    yw = y[w0:w1] - g * x[:, 0]
    beta, *_ = np.linalg.lstsq(X, yw, rcond=None)
    res = yw - X @ beta
    rest = beta[:nt - 1]
    taps = np.concatenate([[g - float(np.sum(rest))], rest])
    return LinearFit(structure, taps, float(beta[nt - 1]), float(beta[nt]) if trend else 0.0, float(res @ res),
                     w1 - w0)


def sse_one(u: np.ndarray, y: np.ndarray, window: tuple[int, int], st: LinearStructure, dt: float, *,
            prefilter: float | None = None, y_cost: np.ndarray | None = None,
            extra: np.ndarray | None = None, mean: float | None = None) -> float:
    """The fit-part SSE of :func:`fit_one` (``y_cost``: ``y`` already in the cost domain, to save the prefilter;
    ``mean``: ``u``'s, :func:`~valve_emulator.diagnosis.fit.linear_kernels.column_mean`, to save its pass).

    Without extra regressors a compiled pass gives the same SSE as fit_one (from the normal equations instead
    of the residual: equal to rounding) at a fraction of the cost of building the regressors. Not for an
    integrator's unfiltered ramps, whose normal equations lose digits to cancellation, nor a held gain.
    """
    m, frac = split_delay(st.delay / dt)
    if extra is not None or window[0] < m + st.ntaps or not _takes_pass(st, prefilter):
        return fit_one(u, y, window, st, dt, prefilter=prefilter, extra=extra).sse
    if y_cost is None:
        y_cost = kernel_array(y if prefilter is None else highpass(y, prefilter))
    return column_sse(kernel_array(u), st.denominator(dt), st.integrating, dt, prefilter, frac, y_cost,
                      window[0], window[1], m, st.ntaps, int(st.integrating and prefilter is None), st.sign, mean)


def _takes_pass(st: LinearStructure, prefilter: float | None) -> bool:
    """Whether :func:`sse_one` scores ``st`` in its compiled pass (where its dead time leaves the window room):
    not an integrator's unfiltered ramps, whose normal equations lose digits to cancellation, nor a held gain."""
    return st.gain is None and not (st.integrating and prefilter is None)


class OneColumn:
    """:func:`sse_one` of one input column against one target on one window, for many structures that differ from
    ``structure`` only in their real time constants and dead time: a polish's evaluations, thousands per diagnosis.

    What does not change from one evaluation to the next (the input as the compiled pass takes it and its mean,
    the target in the cost domain ``y_cost``, the window, the number of taps, the prefilter, the gain's sign) is
    prepared once, and each evaluation calls the pass directly with the denominator of its time constants and the
    split of its dead time: the arguments :func:`sse_one` gives the same pass, so the same SSE to the bit, without
    building a :class:`LinearStructure` and checking it at every evaluation. Only for the structures
    :meth:`serves` names; :meth:`sse` is None where :func:`sse_one` would fit from scratch instead (a dead time
    that leaves the window's first samples without a regressor)."""

    def __init__(self, u: np.ndarray, y_cost: np.ndarray, window: tuple[int, int], structure: LinearStructure,
                 dt: float, prefilter: float | None, mean: float | None = None) -> None:
        self.u = kernel_array(u).reshape(-1)
        self.mean = column_mean(self.u) if mean is None else float(mean)
        self.y = kernel_array(y_cost)
        self.w0, self.w1 = int(window[0]), int(window[1])
        self.ntaps, self.integ, self.dt = structure.ntaps, structure.integrating, float(dt)
        self.highpass, self.lam = prefilter is not None, float(prefilter or 0.0)
        self.sign = float(structure.sign)

    @staticmethod
    def serves(structure: LinearStructure, prefilter: float | None) -> bool:
        """Whether :func:`sse_one` takes the compiled pass for ``structure`` without extra regressors (whatever
        the dead time allows): real poles only, no held gain, no integrator's unfiltered ramps."""
        return not structure.fixed_poles and _takes_pass(structure, prefilter)

    def sse(self, taus: tuple[float, ...], delay: float) -> float | None:
        """``sse_one`` of the structure with time constants ``taus`` and dead time ``delay`` (s); None where it
        would not take the compiled pass."""
        m, frac = split_delay(delay / self.dt)
        if self.w0 < m + self.ntaps:
            return None
        return float(_column_sse(self.u, self.mean, _real_denominator(taus, self.dt), self.integ, self.dt,
                                 self.highpass, self.lam, float(frac), self.y, self.w0, self.w1, int(m), self.ntaps,
                                 0, self.sign))


def prior_term(log_taus: np.ndarray, prior_sorted: list[float]) -> float:
    """The prior on the time constants, ``Σ ((sort(ln τ) − sort(ln τ_nom)) / σ)²`` with σ = :data:`PRIOR_WIDTH`,
    summed as numpy sums it (pairwise; one or two terms: in order), from ``ln τ`` and the sorted ``ln τ_nom``.
    A polish evaluates it hundreds of times, so one or two terms are summed in scalars."""
    if len(prior_sorted) > 2:
        return float(np.sum(((np.sort(log_taus) - np.array(prior_sorted)) / PRIOR_WIDTH) ** 2))
    terms = []
    for v, w in zip(sorted(log_taus.tolist()), prior_sorted):
        d = (v - w) / PRIOR_WIDTH
        terms.append(d * d)
    return float(sum(terms[1:], terms[0]))


def polish(u: np.ndarray, y: np.ndarray, window: tuple[int, int], structure: LinearStructure, dt: float,
           *, free_delay: bool, delay_bounds: tuple[float, float], prefilter: float | None = None,
           prior: tuple[float, ...] | None = None, max_evals: int = 200,
           extra: np.ndarray | None = None) -> LinearFit:
    """Refine the real poles (and the dead time when ``free_delay``) by Nelder–Mead on the output error.

    The taps and offsets are solved by least squares at every evaluation (variable projection), so the
    search has only ``len(taus) (+1)`` dimensions. Time constants are searched on a log scale and kept
    within [dt/20 (or the structure's ``min_tau``), 1e3·record length]; the delay within ``delay_bounds``
    (s). Time constants the structure holds (``taus_held``) stay as they are.

    ``extra`` regressors are fitted jointly at every evaluation (see :func:`fit_one`).

    ``prior`` (time constants of a nominal model, same count as ``structure.taus``) adds the
    log-normal prior, ``Σ ((ln τ − ln τ_nom)/σ)²`` with σ = :data:`PRIOR_WIDTH` (ln 1.25), to ``N ln SSE``
    (−2 log posterior up to a constant; :mod:`~valve_emulator.diagnosis.explain.prior`).
    The data dominate whenever they determine the poles; the prior only decides between near-equivalent
    solutions — notably an actuator lag in series with a re-fitted plant pole, where (6s+1)² and
    (4s+1)(8s+1) differ by one part in ten in the s² term — in favour of the plant the user believes in.
    """
    taus0 = np.log(np.asarray(() if structure.taus_held else structure.taus, dtype=float))
    lo_tau, hi_tau = np.log(structure.min_tau or dt / 20.0), np.log(1e3 * dt * u.shape[0])
    lo_d, hi_d = delay_bounds
    use_prior = prior is not None and len(prior) == taus0.size and taus0.size > 0
    log_prior = np.log(np.asarray(prior, dtype=float)) if use_prior else None
    n = window[1] - window[0]

    def fit(st: LinearStructure) -> LinearFit:
        return fit_one(u, y, window, st, dt, prefilter=prefilter, extra=extra)

    if taus0.size == 0 and not free_delay:
        return fit(structure)
    y_cost = kernel_array(y if prefilter is None else highpass(y, prefilter))
    u1 = kernel_array(u)
    u_mean = column_mean(u1) if u1.ndim == 1 else None   # the same for every evaluation

    # Where sse_one's compiled pass does not apply (extra regressors, an integrator's unfiltered ramps, a held
    # gain) every evaluation is fit_one's: y and the regressors prefiltered once here, and the normal equations
    # of the columns that do not depend on the poles searched made once (FixedColumns); only the input's filter
    # and its taps' rows are redone. The same numbers.
    trend = structure.integrating and prefilter is None
    fixed = None if extra is None and not trend and structure.gain is None else FixedColumns(
        y_cost, window, structure.ntaps, trend, None if extra is None else
        extra if prefilter is None else highpass(extra, prefilter))

    # filter_inputs' own mean of the input (numpy's, as it computes it), and the input less it, once.
    level = None if fixed is None else float(np.asarray(u1, dtype=np.float64)[:, None].mean(axis=0)[0])
    centred = None if fixed is None else np.asarray(u1, dtype=np.float64)[:, None] - level

    def sse(st: LinearStructure) -> float:
        if fixed is None:
            return sse_one(u1, y, window, st, dt, prefilter=prefilter, y_cost=y_cost, mean=u_mean)
        z = _filter_centred(centred, st, dt)[:, 0]
        return fixed.sse(z if prefilter is None else highpass(z, prefilter), st, dt)

    # The cost is evaluated a few hundred times per polish, so its arithmetic is spelled out in scalars
    # (min/max for np.clip, the constructor for dataclasses.replace, a sorted pair for np.sort): the same
    # operations on the same numbers, a third of the time.
    nt, st0 = taus0.size, structure
    prior_sorted = sorted(log_prior.tolist()) if use_prior else None
    lo_t, hi_t, lo_d, hi_d = float(lo_tau), float(hi_tau), float(lo_d), float(hi_d)

    def parts(p: np.ndarray) -> tuple[tuple[float, ...], float]:
        x = p.tolist()
        taus = tuple(float(np.exp(min(max(v, lo_t), hi_t))) for v in x[:nt]) or st0.taus
        return taus, min(max(x[-1], lo_d), hi_d) if free_delay else st0.delay

    def make(p: np.ndarray) -> LinearStructure:
        taus, delay = parts(p)
        return LinearStructure(taus, st0.integrating, st0.fixed_poles, delay, st0.taus_held, st0.gain, st0.sign,
                               st0.min_tau)

    # Most polishes take sse_one's compiled pass at every evaluation: its unchanging arguments prepared once.
    one = OneColumn(u1, y_cost, window, st0, dt, prefilter, u_mean) if (
        fixed is None and u1.ndim == 1 and OneColumn.serves(st0, prefilter)) else None

    def cost(p: np.ndarray) -> float:
        s = None if one is None else one.sse(*parts(p))
        c = log_sse(sse(make(p)) if s is None else s, n)
        if use_prior:
            c += prior_term(p[:nt], prior_sorted)
        return c

    x0 = np.concatenate([taus0, [structure.delay] if free_delay else []])
    step = np.concatenate([np.full(taus0.size, 0.3), [max(dt, 0.1 * structure.delay)] if free_delay else []])
    simplex = np.vstack([x0] + [x0 + np.eye(x0.size)[i] * step[i] for i in range(x0.size)])
    res = nelder_mead(cost, simplex, maxfev=max_evals, xatol=1e-3, fatol=1e-3)
    best = make(res.x) if res.fun <= res.start else structure
    return fit(best)
