r"""The fitted linear part as a continuous transfer function: what a loop config's ``plant`` needs.

The diagnosis fits the linear part in discrete time (:mod:`~valve_emulator.diagnosis.fit.linear`):

.. math:: \hat y_k = \sum_{j=0}^{p-1} b_j z_{k-d-j}, \qquad
          z = \frac{g\,q^{-1}\,(\Delta t)^i}{A_s(q)\,(1 - q^{-1})^i}\,u ,

a ZOH discretisation :math:`H(q) = B(q^{-1})/A(q^{-1})` of some :math:`N(s)/D(s)\,e^{-\theta s}`. The poles
are known in continuous time (the time constants, an integrator, fixed poles); the zeros are in the taps.
Undoing the hold exactly: realise :math:`H` (without the dead time) in state space :math:`(\Phi, \Gamma, C)`;
since :math:`\exp\!\big(\begin{smallmatrix}A & B\\ 0 & 0\end{smallmatrix}\big)\Delta t =
\big(\begin{smallmatrix}\Phi & \Gamma\\ 0 & 1\end{smallmatrix}\big)` for the ZOH of :math:`(A, B)`, the
principal matrix logarithm of the right-hand side divided by :math:`\Delta t` gives :math:`A` and :math:`B`
(integrators included: no :math:`A^{-1}` is needed; the logarithm exists because every pole
:math:`e^{-\Delta t/\tau}` is positive). The dead time θ is kept as fitted. A fractional θ is replayed by the
simulator exactly, where the fit interpolated linearly between samples: the two differ by the first-order
(in Δt/τ) error of that interpolation.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import logm

from valve_emulator.diagnosis.fit.linear import LinearStructure

__all__ = ["discrete_transfer_function", "continuous_transfer_function"]


def discrete_transfer_function(structure: LinearStructure, taps: np.ndarray, dt: float
                               ) -> tuple[np.ndarray, np.ndarray]:
    """``(B, A)``, coefficients in powers of :math:`q^{-1}` of the fitted linear part without its dead time."""
    alpha = structure.denominator(dt)
    den = np.polymul(alpha, [1.0, -1.0]) if structure.integrating else alpha
    gain = float(np.sum(alpha)) * (dt if structure.integrating else 1.0)
    num = gain * np.concatenate([[0.0], np.asarray(taps, dtype=float)])
    return num, den


def _trim(c: np.ndarray, scale: float) -> np.ndarray:
    """Drop leading coefficients that are rounding noise against ``scale``."""
    nz = np.flatnonzero(np.abs(c) > 1e-8 * scale)
    return c[nz[0]:] if nz.size else np.zeros(1)


def continuous_transfer_function(structure: LinearStructure, taps: np.ndarray, dt: float
                                 ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(num, den)`` of :math:`N(s)/D(s)` whose ZOH at ``dt`` is the fitted linear part (see the module
    docstring); ``den`` monic, highest power first, units of the taps per unit input (per second with an
    integrator). The dead time is ``structure.delay``."""
    num_d, den_d = discrete_transfer_function(structure, taps, dt)
    n = den_d.size - 1
    if n == 0:   # a static gain: y_k = b u_{k-1}, which is what the simulator makes of num = [b], den = [1]
        return (float(num_d[1]),), (1.0,)
    num_d = np.concatenate([num_d, np.zeros(n + 1 - num_d.size)])
    A, B, C = _controllable_form(num_d, den_d)
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n:], M[n, n] = A, B, 1.0
    L = np.real(logm(M)) / dt
    num = _numerator(L[:n, :n], L[:n, n:], C)
    num = _trim(np.real(num), float(np.max(np.abs(num))))
    return tuple(float(x) for x in num), tuple(float(x) for x in _denominator(structure))


def _controllable_form(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(A, B, C)`` of the controller canonical realisation of a strictly proper ``num/den`` (same lengths,
    ``num[0]`` zero but for rounding): ``scipy.signal.tf2ss``'s own arithmetic (leading numerator coefficients
    of magnitude ≤ 1e-14 after normalising count as zeros), the same bits, without importing
    :mod:`scipy.signal` (with the :mod:`scipy.stats` it pulls in, ~0.6 s of a first diagnosis)."""
    den = np.trim_zeros(den, "f")
    num, den = num / den[0], den / den[0]
    significant = np.flatnonzero(~(np.abs(num) <= 1e-14))
    zeros = significant[0] if significant.size else num.size - 1   # at least one coefficient stays
    num = np.concatenate([np.zeros(zeros), num[zeros:]])
    k = den.size
    A = np.r_[-np.array([den[1:]]), np.eye(k - 2, k - 1)]
    B = np.eye(k - 1, 1)
    C = num[None, 1:] - np.outer(num[:1], den[1:])
    return A, B, C


def _numerator(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    r"""Numerator of :math:`C (sI - A)^{-1} B`, highest power first: :math:`\det(sI - A + BC) - \det(sI - A)`,
    as ``scipy.signal.ss2tf(A, B, C, 0)`` computes it (the same bits)."""
    return np.poly(A - B @ C) - np.poly(A)


def _denominator(structure: LinearStructure) -> np.ndarray:
    """The monic continuous denominator from the known poles (an integrator's root exactly 0)."""
    poles = [-1.0 / t for t in structure.taus] + list(structure.fixed_poles) + [0.0] * int(structure.integrating)
    return np.real(np.poly(poles)) if poles else np.ones(1)
