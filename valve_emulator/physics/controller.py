r"""PI(D) controllers, position form, ISA parallel-ideal ("standard") structure, as a bank.

At sample k, with action sign :math:`\sigma = +1` (reverse, the default: for a positive process gain
the output falls when PV rises) or :math:`\sigma = -1` (direct),

.. math::
   e_k = \sigma(\mathrm{sp}_k - \mathrm{pv}_k), \qquad
   I_k = I_{k-1} + \frac{\Delta t}{T_i} e_k, \qquad
   \mathrm{op}_k = \mathrm{sat}\big(b + K_c (e_k + I_k + T_d D_k)\big),

with backward-Euler integration and the derivative taken on the measurement only (no kick on a set
point change) through a first-order filter of time constant :math:`T_f = T_d / N`:

.. math:: D_k = \frac{T_f}{T_f + \Delta t} D_{k-1} - \sigma\frac{\mathrm{pv}_k - \mathrm{pv}_{k-1}}{T_f + \Delta t}.

Choices (see e.g. Åström & Hägglund, *Advanced PID Control*, ISA 2006, ch. 3):

* ``ti=None`` or ``inf`` means no integral action (P or PD); ``ti <= 0`` is an error. ``I`` is then
  a constant offset, used only to make manual→auto and tuning changes bumpless.
* ``kc > 0`` always; the sign of the loop is chosen by ``direct``.
* Anti-windup by **conditional integration** (clamping): the integral update is not committed at a
  sample where the unsaturated output :math:`u` computed with it is beyond a limit *and* the error
  would push it further out (:math:`u > \mathrm{op_{max}}, e > 0` or
  :math:`u < \mathrm{op_{min}}, e < 0`); the output is then the limit. The integral therefore stays
  where it was when saturation began, and the output leaves the limit as soon as the error turns.
* Manual: the output is the manual value and the integral tracks,
  :math:`I = (\mathrm{op} - b)/K_c - e - T_d D`. On the first sample in auto the integral is set the
  same way from the last output (and not integrated), so the output continues exactly from the manual
  value. Changing ``kc``/``ti``/``td`` recomputes ``I`` so that :math:`b + K_c(e + I + T_d D)` at the last
  sample's e and D is unchanged.

Kernel for compiled time loops
------------------------------
``pid_step_kernel(sp, pv, kc, ti_inv, td, bias, sign, op_min, op_max, dt, n_filter,
integral, deriv, pv_last, e_last, u_last, op, auto, man_op, init) -> int``

Parameters (n,) float64: ``kc``, ``ti_inv`` (1/Ti, 0 for no integral), ``td``, ``bias``, ``sign``
(+1/−1), ``op_min``, ``op_max``; scalars ``dt``, ``n_filter``. State (n,), mutated: ``integral``,
``deriv``, ``pv_last``, ``e_last``, ``u_last`` (unsaturated output), ``op``; ``auto`` and ``init``
(bool: initialise the integral from the last output at the next auto sample); ``man_op`` (float).
Returns 0, or 1 if ``sp`` / 2 if ``pv`` has a non-finite value (nothing changed).
:meth:`PIDBank.kernel_args` returns every argument after ``pv`` in this order.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import ArrayLike

from valve_emulator.physics._arrays import vector

__all__ = ["PIDBank", "PID", "pid_step_kernel", "DERIVATIVE_FILTER"]

#: N in the derivative filter time constant Td/N.
DERIVATIVE_FILTER = 10.0


@numba.njit(cache=True)
def pid_step_kernel(sp, pv, kc, ti_inv, td, bias, sign, op_min, op_max, dt, n_filter,
                    integral, deriv, pv_last, e_last, u_last, op, auto, man_op, init):  # pragma: no cover
    """Advance every controller one sample in place; see the module docstring for the arguments."""
    n = sp.shape[0]
    for i in range(n):
        if not np.isfinite(sp[i]):
            return 1
        if not np.isfinite(pv[i]):
            return 2
    for i in range(n):
        e = sign[i] * (sp[i] - pv[i])
        tf = td[i] / n_filter
        d = (tf * deriv[i] - sign[i] * (pv[i] - pv_last[i])) / (tf + dt)
        if not auto[i]:
            u = man_op[i]
            integral[i] = (u - bias[i]) / kc[i] - e - td[i] * d
        elif init[i]:
            # First auto sample: continue from the last output, no integration yet.
            integral[i] = (op[i] - bias[i]) / kc[i] - e - td[i] * d
            u = bias[i] + kc[i] * (e + integral[i] + td[i] * d)
            init[i] = False
        else:
            i_new = integral[i] + dt * ti_inv[i] * e
            u = bias[i] + kc[i] * (e + i_new + td[i] * d)
            # Conditional integration: do not commit the update while it would deepen saturation. The
            # output stays at the limit; recomputing it from the old integral instead could park it
            # just inside the limit with the integral frozen for good.
            if not ((u > op_max[i] and e > 0.0) or (u < op_min[i] and e < 0.0)):
                integral[i] = i_new
        deriv[i] = d
        pv_last[i] = pv[i]
        e_last[i] = e
        u_last[i] = u
        op[i] = min(max(u, op_min[i]), op_max[i])
    return 0


def _ti_inverse(ti, n: int) -> np.ndarray:
    """1/Ti per controller; None or inf (per element too) means no integral action -> 0."""
    if ti is None:
        return np.zeros(n)
    try:
        raw = np.broadcast_to(np.asarray(ti, dtype=object), (n,))
    except ValueError:
        raise ValueError(f"ti must be a scalar or have length {n}, got {ti!r}") from None
    out = np.zeros(n)
    for i, v in enumerate(raw):
        if v is None:
            continue
        v = float(v)
        if math.isnan(v) or v <= 0.0:
            raise ValueError(f"ti must be > 0, or None/inf for no integral action, got {v!r}")
        out[i] = 0.0 if math.isinf(v) else 1.0 / v
    return out


class PIDBank:
    """``n`` PI(D) controllers stepped together (see the module docstring for the algorithm).

    Parameters
    ----------
    n : int
        Number of controllers.
    kc : float or array_like
        Proportional gain, > 0.
    ti : float, None or array_like
        Integral time (s); ``None`` or ``inf`` for no integral action.
    td : float or array_like
        Derivative time (s), >= 0.
    bias : float or array_like
        Output at zero error and zero integral (%).
    direct : bool or array_like of bool
        Direct action (e = pv − sp) instead of reverse (e = sp − pv).
    op_min, op_max : float or array_like
        Output limits (%), op_min < op_max.
    dt : float
        Sample time (s), > 0.

    The bank starts in auto with ``reset(pv0=0, sp0=0)``.
    """

    def __init__(self, n: int, *, kc: ArrayLike, ti, td: ArrayLike = 0.0, bias: ArrayLike = 50.0,
                 direct: ArrayLike = False, op_min: ArrayLike = 0.0, op_max: ArrayLike = 100.0,
                 dt: float):
        n = int(n)
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
        self._n, self._dt = n, float(dt)
        self._kc = self._check_kc(vector("kc", kc, n))
        self._ti_inv = _ti_inverse(ti, n)
        self._td = self._check_td(vector("td", td, n))
        self._bias = vector("bias", bias, n)
        self._sign = np.where(vector("direct", direct, n, dtype=bool), -1.0, 1.0)
        self._op_min = vector("op_min", op_min, n)
        self._op_max = vector("op_max", op_max, n)
        for name, arr in (("bias", self._bias), ("op_min", self._op_min), ("op_max", self._op_max)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        if np.any(self._op_min >= self._op_max):
            raise ValueError(f"op_min must be < op_max, got {self._op_min.tolist()} / {self._op_max.tolist()}")
        self._integral = np.zeros(n)
        self._deriv = np.zeros(n)
        self._pv_last = np.zeros(n)
        self._e_last = np.zeros(n)
        self._u_last = np.zeros(n)
        self._op = np.zeros(n)
        self._auto = np.ones(n, dtype=bool)
        self._man_op = np.zeros(n)
        self._init = np.zeros(n, dtype=bool)
        self.reset(0.0, 0.0)

    @staticmethod
    def _check_kc(kc: np.ndarray) -> np.ndarray:
        if not np.all(np.isfinite(kc)) or np.any(kc <= 0):
            raise ValueError(f"kc must be finite and > 0 (use direct= for the sign), got {kc.tolist()}")
        return kc

    @staticmethod
    def _check_td(td: np.ndarray) -> np.ndarray:
        if not np.all(np.isfinite(td)) or np.any(td < 0):
            raise ValueError(f"td must be finite and >= 0, got {td.tolist()}")
        return td

    # -- read-only state -------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of controllers."""
        return self._n

    @property
    def dt(self) -> float:
        """Sample time (s)."""
        return self._dt

    @property
    def op(self) -> np.ndarray:
        """Output at the last sample (%), read-only copy."""
        return self._op.copy()

    @property
    def auto(self) -> np.ndarray:
        """True where the controller is in automatic, read-only copy."""
        return self._auto.copy()

    @property
    def integral(self) -> np.ndarray:
        """Integral state I (error units), read-only copy."""
        return self._integral.copy()

    @property
    def kc(self) -> np.ndarray:
        """Proportional gain, read-only copy."""
        return self._kc.copy()

    @property
    def ti(self) -> np.ndarray:
        """Integral time (s), ``inf`` where there is no integral action; new array."""
        with np.errstate(divide="ignore"):
            return 1.0 / self._ti_inv

    @property
    def td(self) -> np.ndarray:
        """Derivative time (s), read-only copy."""
        return self._td.copy()

    # -- commands --------------------------------------------------------------------------------
    def reset(self, pv0: ArrayLike, sp0: ArrayLike, op0: ArrayLike | None = None) -> None:
        """Start every controller in auto as if it had output ``op0`` (default ``bias``, clipped to the
        limits) at (sp0, pv0).

        With sp0 == pv0 the next ``step(sp0, pv0)`` returns exactly ``op0``.
        """
        pv0 = vector("pv0", pv0, self._n)
        sp0 = vector("sp0", sp0, self._n)
        op0 = np.clip(self._bias, self._op_min, self._op_max) if op0 is None else vector("op0", op0, self._n)
        for name, arr in (("pv0", pv0), ("sp0", sp0), ("op0", op0)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} must be finite, got {arr.tolist()}")
        if np.any(op0 < self._op_min) or np.any(op0 > self._op_max):
            raise ValueError(f"op0 must be within [op_min, op_max], got {op0.tolist()}")
        e0 = self._sign * (sp0 - pv0)
        self._integral[:] = (op0 - self._bias) / self._kc - e0
        self._deriv[:] = 0.0
        self._pv_last[:] = pv0
        self._e_last[:] = e0
        self._u_last[:] = op0
        self._op[:] = op0
        self._auto[:] = True
        self._init[:] = False
        self._man_op[:] = self._op

    def step(self, sp: ArrayLike, pv: ArrayLike) -> np.ndarray:
        """Output at this sample for set points ``sp`` and measurements ``pv`` (shape (n,)); new array.

        Raises ValueError naming ``sp``/``pv`` for a wrong shape or non-finite value (nothing changes).
        """
        sp_a = self._input("sp", sp)
        pv_a = self._input("pv", pv)
        code = pid_step_kernel(sp_a, pv_a, *self.kernel_args())
        if code:
            bad = sp_a if code == 1 else pv_a
            name = "sp" if code == 1 else "pv"
            raise ValueError(f"{name} must be finite, got {bad.tolist()}")
        return self._op.copy()

    def _input(self, name: str, value) -> np.ndarray:
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape == (self._n,):
            return value
        arr = np.asarray(value, dtype=np.float64)
        if arr.shape != (self._n,):
            if arr.size != 1:
                raise ValueError(f"{name} must have shape ({self._n},), got {arr.shape}")
            arr = np.full(self._n, float(arr.reshape(-1)[0]))
        return arr

    def _select(self, index_or_mask) -> np.ndarray:
        sel = np.zeros(self._n, dtype=bool)
        idx = np.asarray(index_or_mask)
        if idx.dtype == bool:
            if idx.shape != (self._n,):
                raise ValueError(f"index_or_mask as a mask must have shape ({self._n},), got {idx.shape}")
            sel[:] = idx
        else:
            if not np.issubdtype(idx.dtype, np.integer) or np.any((idx < -self._n) | (idx >= self._n)):
                raise ValueError(f"index_or_mask must be indices in [0, {self._n}), got {index_or_mask!r}")
            sel[idx] = True
        return sel

    def set_manual(self, index_or_mask, op: ArrayLike) -> None:
        """Put the selected controllers in manual with output ``op`` (within the limits), from the next step."""
        sel = self._select(index_or_mask)
        k = int(sel.sum())
        try:
            val = np.array(np.broadcast_to(np.asarray(op, dtype=float), (k,)))
        except ValueError:
            raise ValueError(f"op must be a scalar or have {k} values, got {op!r}") from None
        if not np.all(np.isfinite(val)) or np.any(val < self._op_min[sel]) or np.any(val > self._op_max[sel]):
            raise ValueError(f"op must be finite and within [op_min, op_max], got {val.tolist()}")
        self._man_op[sel] = val
        self._auto[sel] = False
        self._init[sel] = False

    def set_auto(self, index_or_mask) -> None:
        """Switch the selected controllers to auto; the output continues bumplessly from its last value."""
        sel = self._select(index_or_mask) & ~self._auto
        self._auto[sel] = True
        self._init[sel] = True

    def set_tuning(self, index_or_mask, *, kc: float | None = None, ti: float | None = None,
                   td: float | None = None) -> None:
        """Change tuning of the selected controllers bumplessly. ``None`` leaves a value unchanged;
        pass ``ti=math.inf`` for no integral action.

        The integral is recomputed so that b + Kc(e + I + Td·D) at the last sample is unchanged.
        """
        sel = self._select(index_or_mask)
        k = int(sel.sum())
        kc_new = self._kc.copy()
        td_new = self._td.copy()
        ti_inv_new = self._ti_inv.copy()
        if kc is not None:
            kc_new[sel] = self._check_kc(vector("kc", kc, k))
        if td is not None:
            td_new[sel] = self._check_td(vector("td", td, k))
        if ti is not None:
            ti_inv_new[sel] = _ti_inverse(ti, k)
        e, d = self._e_last, self._deriv
        # Keep the last unsaturated output: kc_old(e + I_old + td_old d) = kc_new(e + I_new + td_new d).
        i_new = self._kc * (e + self._integral + self._td * d) / kc_new - e - td_new * d
        self._integral[sel] = i_new[sel]
        # in place: a loop bank keeps these arrays as rows of its own (see kernel_args)
        self._kc[:], self._td[:], self._ti_inv[:] = kc_new, td_new, ti_inv_new

    def kernel_args(self) -> tuple:
        """Arguments of :func:`pid_step_kernel` after ``pv``; the arrays are the bank's live state, changed only in
        place (a loop bank may hold them as rows of one array)."""
        return (self._kc, self._ti_inv, self._td, self._bias, self._sign, self._op_min, self._op_max,
                self._dt, DERIVATIVE_FILTER, self._integral, self._deriv, self._pv_last, self._e_last,
                self._u_last, self._op, self._auto, self._man_op, self._init)

    def live_settings(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``kc``, ``1/ti`` (0: no integral action), ``td`` and ``auto`` as the bank's own arrays, not copies: for a
        compiled reader at every sample (the device's image encoder), which must not write them. A change of tuning
        writes them in place."""
        return self._kc, self._ti_inv, self._td, self._auto

    def kernel_output(self) -> np.ndarray:
        """The output array :func:`pid_step_kernel` writes, the one inside :meth:`kernel_args` (live state:
        for a caller that composes the kernel into its own compiled loop, not for reading -- use ``op``)."""
        return self._op


class PID:
    """One controller: a :class:`PIDBank` of one with scalar in/out. Same keywords as PIDBank."""

    def __init__(self, *, kc: float, ti, td: float = 0.0, bias: float = 50.0, direct: bool = False,
                 op_min: float = 0.0, op_max: float = 100.0, dt: float):
        self._bank = PIDBank(1, kc=kc, ti=ti, td=td, bias=bias, direct=direct, op_min=op_min,
                             op_max=op_max, dt=dt)

    def __call__(self, sp: float, pv: float) -> float:
        """Output at this sample."""
        return float(self._bank.step(np.array([sp], dtype=float), np.array([pv], dtype=float))[0])

    def reset(self, pv0: float, sp0: float, op0: float | None = None) -> None:
        """See :meth:`PIDBank.reset`."""
        self._bank.reset(pv0, sp0, op0)

    def set_manual(self, op: float) -> None:
        """Manual with output ``op``."""
        self._bank.set_manual(0, op)

    def set_auto(self) -> None:
        """Back to auto, bumplessly."""
        self._bank.set_auto(0)

    def set_tuning(self, *, kc: float | None = None, ti: float | None = None, td: float | None = None) -> None:
        """See :meth:`PIDBank.set_tuning`."""
        self._bank.set_tuning(0, kc=kc, ti=ti, td=td)

    @property
    def op(self) -> float:
        """Output at the last sample."""
        return float(self._bank.op[0])

    @property
    def auto(self) -> bool:
        """True in automatic."""
        return bool(self._bank.auto[0])
