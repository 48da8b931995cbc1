r"""Linear plants with dead time, discretised exactly by zero-order hold, stepped as a bank.

A plant is a transfer function with dead time

.. math:: G(s) = \frac{b_0 s^q + \dots + b_q}{a_0 s^p + \dots + a_p}\, e^{-\theta s},
   \qquad q \le p,

driven by the flow deviation :math:`u - u_0` (% of valve flow) and read as
:math:`\mathrm{pv} = \mathrm{pv}_0 + y` (engineering units).

Exact ZOH with a fractional dead time
-------------------------------------
Write :math:`\theta = (m + f)\,\Delta t` with integer :math:`m \ge 0` and :math:`0 \le f < 1`, and let
the input be held, :math:`u(t) = u_k` on :math:`[t_k, t_{k+1})`. The delayed input seen by the
state-space realisation :math:`\dot x = A x + B u_d`, :math:`y = C x + D u_d` is, over
:math:`[t_k, t_{k+1})`, :math:`u_{k-m-1}` for the first :math:`f\Delta t` and :math:`u_{k-m}` for the rest.
Splitting the ZOH convolution integral at :math:`f\Delta t` gives exactly

.. math::
   x_{k+1} = \Phi x_k + \Gamma_1 u_{k-m} + \Gamma_0 u_{k-m-1},\qquad
   \Phi = e^{A\Delta t},\quad
   \Gamma_1 = \int_0^{(1-f)\Delta t} e^{A\tau}d\tau\,B,\quad
   \Gamma_0 = e^{A(1-f)\Delta t}\int_0^{f\Delta t} e^{A\tau}d\tau\,B

(the modified z-transform / state augmentation of Åström & Wittenmark, *Computer-Controlled Systems*,
3rd ed., §2.3). Each integral comes from one matrix exponential of the augmented matrix,
:math:`\exp\!\big(\begin{smallmatrix}A & B\\ 0 & 0\end{smallmatrix}\big)h =
\big(\begin{smallmatrix}e^{Ah} & \int_0^h e^{A\tau}d\tau B\\ 0 & 1\end{smallmatrix}\big)`, so integrators
(singular :math:`A`) need no :math:`A^{-1}`. With :math:`f = 0`, :math:`\Gamma_0 = 0`.

PV convention: ``pv`` at :math:`t_k` is :math:`C x_k + D u_{k-1-m}`, the continuous output just before
:math:`t_k` (:math:`y(t_k^-)`); it equals :math:`y(t_k)` except at an instant where the delayed input
switches and :math:`D \ne 0`.

Kernel for compiled time loops
------------------------------
``plant_step_kernel(u, u0, pv0, A, B0, B1, C, D, m, buf, head, x, ud, pv, work) -> int``

====== ============ ===================================================================
name   shape/dtype  meaning
====== ============ ===================================================================
u      (n,) f8      flow (%) applied over :math:`[t_k, t_k+\Delta t)` (read only)
u0     (n,) f8      operating-point flow
pv0    (n,) f8      PV at the operating point
A      (n,p,p) f8   :math:`\Phi`, zero-padded to the largest order p in the bank
B0     (n,p) f8     :math:`\Gamma_0` (multiplies the older input :math:`u_{k-m-1}`)
B1     (n,p) f8     :math:`\Gamma_1` (multiplies :math:`u_{k-m}`)
C      (n,p) f8     output row
D      (n,) f8      feed-through
m      (n,) i8      integer delay in samples
buf    (n,L) f8     ring buffer of input deviations :math:`u-u_0`, L ≥ max(m)+2 (mutated)
head   (1,) i8      ring-buffer column of the newest input (mutated)
x      (n,p) f8     state (mutated)
ud     (n,) f8      delayed input in effect just before the next sample (mutated)
pv     (n,) f8      PV at :math:`t_{k+1}` (output, mutated)
work   (p,) f8      scratch
====== ============ ===================================================================

It returns ``-1``, or the index of the first non-finite ``u`` — in which case nothing was changed.
:meth:`PlantBank.kernel_args` returns every argument after ``u`` in this order.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import expm

from valve_emulator.physics._arrays import vector

__all__ = [
    "DiscretePlant",
    "PlantBank",
    "transfer_function_to_zoh",
    "transfer_functions_to_zoh",
    "check_transfer_function",
    "fopdt",
    "integrator",
    "plant_step_kernel",
    "MAX_DELAY_SAMPLES",
]

#: Largest integer dead time in samples (sizes the ring buffer; guards against delay/dt typos).
MAX_DELAY_SAMPLES = 1_000_000
# A delay within this many samples of an integer is that integer: 0.3/0.1 is 2.9999999999999996.
_SNAP = 1e-9


@dataclass(frozen=True, eq=False)
class DiscretePlant:
    """Exact ZOH discretisation of one transfer function with dead time (arrays are read-only).

    Attributes
    ----------
    A : ndarray (p, p)
        :math:`\\Phi = e^{A_c \\Delta t}`.
    B0, B1 : ndarray (p,)
        :math:`\\Gamma_0` (older input, fractional part of the delay) and :math:`\\Gamma_1` (newer input).
    C : ndarray (p,)
    D : float
    m : int
        Integer part of the delay in samples.
    dt : float
    frac : float
        Fractional part f of the delay, ``delay = (m + frac) * dt``.
    x_rest : ndarray (p,)
        State at rest for a unit constant input deviation (zeros for integrating plants).
    integrating : bool
        The denominator has a root at s = 0 (no steady state for a non-zero input deviation).
    """

    A: np.ndarray
    B0: np.ndarray
    B1: np.ndarray
    C: np.ndarray
    D: float
    m: int
    dt: float
    frac: float = 0.0
    x_rest: np.ndarray | None = None
    integrating: bool = False

    @property
    def order(self) -> int:
        """Number of states p."""
        return self.A.shape[0]

    @property
    def delay(self) -> float:
        """Dead time in seconds, (m + frac)·dt."""
        return (self.m + self.frac) * self.dt


def _coefficients(name: str, value: ArrayLike) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D coefficient sequence, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has non-finite coefficients: {arr.tolist()}")
    return arr


def _zoh_batch(A: np.ndarray, B: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(e^{A h}, ∫_0^h e^{Aτ}dτ B)`` for stacks ``A`` (q, p, p), ``B`` (q, p), ``h`` (q,).

    First order in closed form (e^{-a h} and (1 − e^{-a h})/a, by ``expm1``; h when a = 0), vectorised;
    higher orders from the exponential of the augmented matrix [[A h, B h], [0, 0]] (no A^{-1}).
    """
    q, p = B.shape
    if p == 0:
        return np.ones((q, 0, 0)), np.zeros((q, 0))
    if p == 1:
        a = A[:, 0, 0]
        e = np.exp(a * h)
        small = a == 0.0
        g = np.where(small, h, np.expm1(a * h) / np.where(small, 1.0, a)) * B[:, 0]
        return e[:, None, None], g[:, None]
    M = np.zeros((q, p + 1, p + 1))
    M[:, :p, :p] = A * h[:, None, None]
    M[:, :p, p] = B * h[:, None]
    E = expm(M)
    return E[:, :p, :p], E[:, :p, p]


def check_transfer_function(num: ArrayLike, den: ArrayLike, delay: float, dt: float
                            ) -> tuple[np.ndarray, np.ndarray, int, float, float]:
    """Validate ``num(s)/den(s)·exp(-delay·s)`` at step ``dt`` without discretising it.

    Returns ``(num, den, m, f, dt)``: the coefficients normalised (leading zeros dropped, ``den`` monic) and
    the delay split as θ = (m + f)·dt. Raises the :class:`ValueError` of :func:`transfer_function_to_zoh`.
    """
    num_a = _coefficients("num", num)
    den_a = _coefficients("den", den)
    dt = float(dt)
    delay = float(delay)
    if not np.isfinite(dt) or dt <= 0.0:
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    if not np.isfinite(delay) or delay < 0.0:
        raise ValueError(f"delay must be a finite number >= 0, got {delay!r}")
    nz = np.flatnonzero(den_a)
    if nz.size == 0:
        raise ValueError(f"den must have a non-zero coefficient, got {den_a.tolist()}")
    den_a = den_a[nz[0]:]
    nzn = np.flatnonzero(num_a)
    num_a = num_a[nzn[0]:] if nzn.size else np.zeros(1)
    if num_a.size > den_a.size:
        raise ValueError(
            f"num has degree {num_a.size - 1} > degree {den_a.size - 1} of den: improper transfer function"
        )
    num_a = num_a / den_a[0]
    den_a = den_a / den_a[0]

    m, f = _split_delay(delay, dt)
    return num_a, den_a, m, f, dt


def _split_delay(delay: float, dt: float) -> tuple[int, float]:
    """θ = (m + f)·dt, snapping a θ/dt within :data:`_SNAP` of an integer to it."""
    ratio = delay / dt
    if ratio > MAX_DELAY_SAMPLES:
        raise ValueError(f"delay is {ratio:.6g} samples of dt={dt}, more than {MAX_DELAY_SAMPLES}")
    m = round(ratio)
    if abs(ratio - m) <= _SNAP * max(1.0, ratio):
        return int(m), 0.0
    m = math.floor(ratio)
    return int(m), float(ratio - m)


def _check_batch(plants: Sequence[tuple]) -> list[tuple | None]:
    """:func:`check_transfer_function` of the usual plants in batches, None for the others.

    Usual: ``num`` and ``den`` tuples or lists of numbers, grouped by their lengths, with finite coefficients,
    no leading zeros, a proper transfer function, finite ``delay >= 0`` and ``dt > 0``. numpy's overhead on
    arrays of two numbers, once per plant, dominated building 10^5 plants. The results are those of the
    general path, bit for bit (the same IEEE divisions and roundings); it checks (and reports) the others.
    """
    out: list[tuple | None] = [None] * len(plants)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, (num, den, _, _) in enumerate(plants):
        if isinstance(num, (tuple, list)) and isinstance(den, (tuple, list)) and 0 < len(num) <= len(den):
            groups.setdefault((len(num), len(den)), []).append(i)
    for idx in groups.values():
        try:
            N = np.array([plants[i][0] for i in idx], dtype=float)
            D = np.array([plants[i][1] for i in idx], dtype=float)
            delay = np.array([plants[i][2] for i in idx], dtype=float)
            dt = np.array([plants[i][3] for i in idx], dtype=float)
        except (TypeError, ValueError):
            continue   # not numbers: the general path says which
        with np.errstate(all="ignore"):
            ok = ((N[:, 0] != 0.0) & (D[:, 0] != 0.0) & np.isfinite(N).all(axis=1) & np.isfinite(D).all(axis=1)
                  & np.isfinite(dt) & (dt > 0.0) & np.isfinite(delay) & (delay >= 0.0))
            ratio = delay / dt
            ok &= ratio <= MAX_DELAY_SAMPLES
            num_a, den_a = N / D[:, :1], D / D[:, :1]
            m = np.round(ratio)   # half to even, as Python's round
            snap = np.abs(ratio - m) <= _SNAP * np.maximum(1.0, ratio)
            m = np.where(snap, m, np.floor(ratio))
            f = np.where(snap, 0.0, ratio - m)
        for j in np.flatnonzero(ok).tolist():
            out[idx[j]] = (num_a[j], den_a[j], int(m[j]), float(f[j]), float(dt[j]))
    return out


def transfer_function_to_zoh(num: ArrayLike, den: ArrayLike, delay: float, dt: float) -> DiscretePlant:
    """Discretise ``num(s)/den(s)·exp(-delay·s)`` exactly by zero-order hold at step ``dt``.

    Parameters
    ----------
    num, den : array_like
        Coefficients, highest power first (as ``scipy.signal``). Leading zeros are ignored.
    delay : float
        Dead time θ ≥ 0 in seconds, split as θ = (m + f)·dt; a θ/dt within 1e-9 of an integer is
        taken as that integer.
    dt : float
        Sample time > 0.

    Returns
    -------
    DiscretePlant

    Raises
    ------
    ValueError
        Naming ``num``, ``den``, ``delay`` or ``dt``: non-finite values, empty or zero ``den``,
        improper transfer function (deg num > deg den), negative delay, dt ≤ 0, or a delay longer than
        :data:`MAX_DELAY_SAMPLES` samples.
    """
    return transfer_functions_to_zoh([(num, den, delay, dt)])[0]


def transfer_functions_to_zoh(plants: Sequence[tuple]) -> list[DiscretePlant]:
    """:func:`transfer_function_to_zoh` of many ``(num, den, delay, dt)`` at once (same results).

    Plants of one order share three batched matrix exponentials (closed form and vectorised for first-order
    plants, scipy's stacked ``expm`` above), which is what makes building a bank of 10^5 loops with different
    plants take seconds, not minutes. Raises the
    :class:`ValueError` of the first plant that cannot be discretised, prefixed by its index when there are
    several.
    """
    checked = _check_batch(plants)
    for i, args in enumerate(plants):
        if checked[i] is not None:
            continue
        try:
            checked[i] = check_transfer_function(*args)
        except ValueError as exc:
            raise (exc if len(plants) == 1 else ValueError(f"plant {i}: {exc}")) from None
    out: list[DiscretePlant | None] = [None] * len(checked)
    by_order: dict[int, list[int]] = {}
    for i, (_, den_a, *_rest) in enumerate(checked):
        by_order.setdefault(den_a.size - 1, []).append(i)
    for p, idx in by_order.items():
        Ac, Bc, Cc, Dc = _realise_batch([checked[i][0] for i in idx], np.array([checked[i][1] for i in idx]))
        f = np.array([checked[i][3] for i in idx])
        dt = np.array([checked[i][4] for i in idx])
        Phi, _ = _zoh_batch(Ac, Bc, dt)
        Phi1, G1 = _zoh_batch(Ac, Bc, (1.0 - f) * dt)
        G0 = np.zeros_like(G1)
        frac = np.flatnonzero(f > 0.0)
        if frac.size:
            _, g0 = _zoh_batch(Ac[frac], Bc[frac], f[frac] * dt[frac])
            G0[frac] = np.einsum("qij,qj->qi", Phi1[frac], g0)
        integrating = np.array([checked[i][1].size > 1 and checked[i][1][-1] == 0.0 for i in idx], dtype=bool)
        x_rest = np.zeros((len(idx), p))
        rest = np.flatnonzero(~integrating) if p else np.zeros(0, dtype=int)
        if rest.size:
            # Continuous equilibrium A x + B = 0 is also the fixed point of the exact discrete map.
            x_rest[rest] = np.linalg.solve(Ac[rest], -Bc[rest][:, :, None])[:, :, 0]
        # Each plant's arrays are read-only views of these stacks (one flag each, not one per plant).
        Phi, G0, G1, Cc, x_rest = (np.ascontiguousarray(a) for a in (Phi, G0, G1, Cc, x_rest))
        for arr in (Phi, G0, G1, Cc, x_rest):
            arr.setflags(write=False)
        for j, i in enumerate(idx):
            _, _, m, fj, dtj = checked[i]
            out[i] = DiscretePlant(A=Phi[j], B0=G0[j], B1=G1[j], C=Cc[j], D=float(Dc[j]), m=m, dt=dtj, frac=fj,
                                   x_rest=x_rest[j], integrating=bool(integrating[j]))
    return out


def _realise_batch(nums: list[np.ndarray], dens: np.ndarray):
    """Controllable canonical realisations (A, B, C, D) of num/den for plants of one order p at once: ``dens``
    (q, p + 1) monic, ``nums`` of length ≤ p + 1; returns stacks A (q, p, p), B (q, p), C (q, p), D (q,)."""
    q, p = dens.shape[0], dens.shape[1] - 1
    b = np.zeros((q, p + 1))
    for j, num in enumerate(nums):
        b[j, p + 1 - num.size:] = num
    d = b[:, 0]
    A = np.zeros((q, p, p))
    B = np.zeros((q, p))
    if p:
        A[:, 0, :] = -dens[:, 1:]
        A[:, np.arange(1, p), np.arange(p - 1)] = 1.0
        B[:, 0] = 1.0
    C = b[:, 1:] - d[:, None] * dens[:, 1:]  # strictly proper remainder after taking out the feed-through d
    return A, B, C, d


def fopdt(gain: float, tau: float, delay: float) -> tuple[list[float], list[float], float]:
    """First order plus dead time K·e^{-θs}/(τs+1) as ``(num, den, delay)``; ``tau=0`` is a pure gain."""
    if not np.isfinite(tau) or tau < 0.0:
        raise ValueError(f"tau must be a finite number >= 0, got {tau!r}")
    den = [float(tau), 1.0] if tau > 0.0 else [1.0]
    return [float(gain)], den, float(delay)


def integrator(gain: float, delay: float = 0.0) -> tuple[list[float], list[float], float]:
    """Integrator with dead time K·e^{-θs}/s as ``(num, den, delay)``."""
    return [float(gain)], [1.0, 0.0], float(delay)


@numba.njit(cache=True)
def plant_step_kernel(u, u0, pv0, A, B0, B1, C, D, m, buf, head, x, ud, pv, work):  # pragma: no cover
    """Advance every plant one sample in place; see the module docstring for the arguments."""
    n = u.shape[0]
    for i in range(n):
        if not np.isfinite(u[i]):
            return i  # reject before touching any state
    L = buf.shape[1]
    p = x.shape[1]
    h = head[0] + 1
    if h == L:
        h = 0
    head[0] = h
    if p == 1:
        _first_order_step(u, u0, pv0, A, B0, B1, C, D, m, buf, h, x, ud, pv)
        return -1
    for i in range(n):
        unew, uold = _delayed(buf, i, h, u[i] - u0[i], m[i])
        # Padded rows/columns are exact zeros, so a padded plant adds only +0.0 terms in the same
        # order as its unpadded self: bank results equal single-plant results bit for bit.
        for r in range(p):
            s = B1[i, r] * unew + B0[i, r] * uold
            for c in range(p):
                s += A[i, r, c] * x[i, c]
            work[r] = s
        y = D[i] * unew
        for r in range(p):
            x[i, r] = work[r]
            y += C[i, r] * work[r]
        ud[i] = unew
        pv[i] = pv0[i] + y
    return -1


@numba.njit(cache=True, inline="always")
def _delayed(buf, i, h, du, m):  # pragma: no cover - compiled
    """Write plant ``i``'s input deviation ``du`` at the ring's head ``h``; return its inputs ``m`` and
    ``m + 1`` samples ago (the newer and older input of the fractional delay)."""
    L = buf.shape[1]
    buf[i, h] = du
    j = h - m
    if j < 0:
        j += L
    k = j - 1
    if k < 0:
        k += L
    return buf[i, j], buf[i, k]


@numba.njit(cache=True, inline="always")
def _first_order_step(u, u0, pv0, A, B0, B1, C, D, m, buf, h, x, ud, pv):  # pragma: no cover - compiled
    """:func:`plant_step_kernel`'s loop for a bank of order 1 (every plant first order or a pure gain, the
    usual fleet): the same operations in the same order, without the loops over the state (a quarter of the
    plant's time per tick at 10^5 loops)."""
    for i in range(u.shape[0]):
        unew, uold = _delayed(buf, i, h, u[i] - u0[i], m[i])
        s = B1[i, 0] * unew + B0[i, 0] * uold + A[i, 0, 0] * x[i, 0]
        x[i, 0] = s
        ud[i] = unew
        pv[i] = pv0[i] + (D[i] * unew + C[i, 0] * s)


class PlantBank:
    """``n`` plants stepped together: pv = pv0 + G(s)·(u − u0).

    Plants may differ in order (state-space zero-padded to the largest order) and in delay (ring
    buffers of a common length); they must share ``dt``. The bank starts at rest with ``u = u0``.

    Parameters
    ----------
    plants : sequence of DiscretePlant
    u0 : array_like
        Operating-point flow (%), scalar or (n,).
    pv0 : array_like
        PV at the operating point (engineering units), scalar or (n,).
    """

    def __init__(self, plants: Sequence[DiscretePlant], *, u0: ArrayLike, pv0: ArrayLike):
        plants = list(plants)
        if not plants or not all(isinstance(p, DiscretePlant) for p in plants):
            raise ValueError("plants must be a non-empty sequence of DiscretePlant")
        dts = {p.dt for p in plants}
        if len(dts) != 1:
            raise ValueError(f"plants must share one dt, got {sorted(dts)}")
        n = len(plants)
        self._n = n
        self._dt = plants[0].dt
        self._u0 = vector("u0", u0, n, finite=True)
        self._pv0 = vector("pv0", pv0, n, finite=True)
        p = max(1, max(pl.order for pl in plants))
        self._A = np.zeros((n, p, p))
        self._B0 = np.zeros((n, p))
        self._B1 = np.zeros((n, p))
        self._C = np.zeros((n, p))
        self._xr = np.zeros((n, p))
        for i, pl in enumerate(plants):
            q = pl.order
            self._A[i, :q, :q] = pl.A
            self._B0[i, :q] = pl.B0
            self._B1[i, :q] = pl.B1
            self._C[i, :q] = pl.C
            if pl.x_rest is not None:
                self._xr[i, :q] = pl.x_rest
        self._D = np.array([pl.D for pl in plants])
        self._m = np.array([pl.m for pl in plants], dtype=np.int64)
        self._buf = np.zeros((n, int(self._m.max()) + 2))
        self._head = np.zeros(1, dtype=np.int64)
        self._x = np.zeros((n, p))
        self._ud = np.zeros(n)
        self._pv = self._pv0.copy()
        self._work = np.zeros(p)
        self.reset(self._u0)

    @property
    def n(self) -> int:
        """Number of plants."""
        return self._n

    @property
    def dt(self) -> float:
        """Common sample time (s)."""
        return self._dt

    @property
    def pv(self) -> np.ndarray:
        """Noise-free PV at the current sample instant (read-only view, length n)."""
        view = self._pv.view()
        view.setflags(write=False)
        return view

    def reset(self, u_init: ArrayLike) -> None:
        """Put every plant at rest for the constant input ``u_init`` (scalar or (n,)).

        The state is the equilibrium for u_init − u0 (x = 0, i.e. pv = pv0, for integrating plants)
        and the delay buffers are filled with u_init, so pv = pv0 + G(0)·(u_init − u0).
        """
        du = vector("u_init", u_init, self._n, finite=True) - self._u0
        self._x[:] = self._xr * du[:, None]
        self._buf[:] = du[:, None]
        self._head[0] = 0
        self._ud[:] = du
        self._pv[:] = self._pv0 + np.einsum("ij,ij->i", self._C, self._x) + self._D * du

    def step(self, u: np.ndarray) -> np.ndarray:
        """Apply flow ``u`` (%, shape (n,)) over [t_k, t_k+dt); return PV at t_{k+1} (a new array).

        Raises ValueError naming ``u`` for a wrong shape or a non-finite value; the state is then
        unchanged.
        """
        if not (isinstance(u, np.ndarray) and u.dtype == np.float64 and u.shape == (self._n,)
                and u.flags.c_contiguous):
            u = np.ascontiguousarray(u, dtype=np.float64)
            if u.shape != (self._n,):
                if u.size == 1:
                    u = np.full(self._n, float(u.reshape(-1)[0]))
                else:
                    raise ValueError(f"u must have shape ({self._n},), got {u.shape}")
        bad = plant_step_kernel(u, *self.kernel_args())
        if bad >= 0:
            raise ValueError(f"u[{bad}] must be finite, got {u[bad]!r}")
        return self._pv.copy()

    def kernel_args(self) -> tuple:
        """Arguments of :func:`plant_step_kernel` after ``u``; the arrays are the bank's live state."""
        return (self._u0, self._pv0, self._A, self._B0, self._B1, self._C, self._D, self._m,
                self._buf, self._head, self._x, self._ud, self._pv, self._work)

    def kernel_output(self) -> np.ndarray:
        """The PV array :func:`plant_step_kernel` writes, the one inside :meth:`kernel_args` (live state:
        for a caller that composes the kernel into its own compiled loop, not for reading -- use ``pv``)."""
        return self._pv
