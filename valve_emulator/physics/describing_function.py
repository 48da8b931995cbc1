r"""Describing function of the (S, J) stiction model.

Source: Choudhury, Thornhill & Shah, "Modelling valve stiction", Control Engineering Practice 13 (2005)
641-658, section on the describing function. ``S`` (deadband + stickband, on the OP axis) and ``J`` (slip
jump, on the MV axis) follow the 2005 convention used throughout the package.

For a valve input ``OP = A sin(wt)`` the valve output in steady oscillation is piecewise: it follows
``OP - d (S - J)/2`` while moving in direction ``d`` and is held from each peak of OP until OP has come
back by ``S``. Its first harmonic divided by the input's, ``N(A)``, does not depend on ``w``:

.. math::

    N(A) = 0 \quad (A \le S/2), \qquad
    N(A) = -\frac{P - jQ}{\pi A} \quad (A > S/2),

    \phi = \arcsin\frac{A - S}{A}, \qquad
    P = \tfrac{A}{2}\sin 2\phi - 2A\cos\phi - A\left(\tfrac{\pi}{2} + \phi\right)
        + 2(S - J)\cos\phi,

    Q = -\tfrac{3A}{2} + \tfrac{A}{2}\cos 2\phi + 2A\sin\phi - 2(S - J)\sin\phi .

The valve sticks at each peak of OP and slips when OP has come back by ``S``, to ``+-(A - S)``: at phase
``phi`` before OP's next crossing of its mean. The formula holds on the whole range ``A > S/2``, including
``S/2 < A < S`` where ``phi`` is negative (the valve slips only after OP has crossed its mean); this was
checked against the ``"kano"`` state machine to about 1e-5 relative (``tests/physics/test_describing_function.py``).

Limits worth knowing: ``J = 0`` gives the classical backlash describing function (``N -> 0`` as
``A -> S/2``); for ``J > 0``, ``N(S/2^+) = -2jJ/(\pi A)``, the square wave of height ``J`` that a valve
makes when it slips by ``J`` at each reversal and otherwise stays put, so ``N`` jumps at ``A = S/2``;
``N -> 1`` as ``A -> infinity``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["describing_function", "negative_reciprocal"]


def _check_parameters(S: float, J: float) -> tuple[float, float]:
    S = float(S)
    J = float(J)
    if not np.isfinite(S) or S < 0:
        raise ValueError(f"S must be a finite number >= 0 (% of valve travel), got {S!r}")
    if not np.isfinite(J) or J < 0:
        raise ValueError(f"J must be a finite number >= 0 (% of valve travel), got {J!r}")
    return S, J


def describing_function(A: ArrayLike, S: float, J: float) -> np.ndarray:
    """Describing function ``N(A)`` of the stiction model for input ``A sin(wt)``.

    Parameters
    ----------
    A : array_like
        Amplitude(s) of the sinusoidal valve input OP, % travel, each finite and ``>= 0``.
    S, J : float
        Deadband + stickband and slip jump, % travel (2005 convention), ``>= 0``.

    Returns
    -------
    numpy.ndarray of complex, same shape as ``A``
        ``N(A)``: the first Fourier coefficient of MV as ``b1 + j a1`` (``MV ~ a1 cos + b1 sin``) divided by
        ``A``. Zero where ``A <= S/2`` (the valve never moves).

    Raises
    ------
    ValueError
        If ``S`` or ``J`` is negative or not finite, or any ``A`` is negative or not finite.

    Notes
    -----
    See the module docstring for the formula (Choudhury, Thornhill & Shah 2005).
    """
    S, J = _check_parameters(S, J)
    a = np.asarray(A, dtype=float)
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError(f"A must be finite and >= 0 (% of valve travel), got {A!r}")
    out = np.zeros(a.shape, dtype=complex)
    moving = a > 0.5 * S
    if S == 0.0:
        # With S = 0 the valve moves for every A > 0; A = 0 is no input at all.
        moving = a > 0.0
    am = a[moving]
    # The argument lies in [-1, 1) mathematically; clip the last ulp that rounding can add next to A = S/2.
    phi = np.arcsin(np.clip((am - S) / am, -1.0, 1.0))
    cos_phi = np.cos(phi)
    sin_phi = np.sin(phi)
    P = 0.5 * am * np.sin(2 * phi) - 2 * am * cos_phi - am * (0.5 * np.pi + phi) + 2 * (S - J) * cos_phi
    Q = -1.5 * am + 0.5 * am * np.cos(2 * phi) + 2 * am * sin_phi - 2 * (S - J) * sin_phi
    out[moving] = -(P - 1j * Q) / (np.pi * am)
    return out


def negative_reciprocal(A: ArrayLike, S: float, J: float) -> np.ndarray:
    """The critical locus ``-1/N(A)`` used in harmonic balance (``L(jw) = -1/N(A)``).

    Same parameters as :func:`describing_function`. Where ``N(A) = 0`` (``A <= S/2``) the locus is at
    infinity and the value returned is ``nan + nan j``, so that it cannot be mistaken for a point.
    """
    n = describing_function(A, S, J)
    out = np.full(n.shape, complex(np.nan, np.nan))
    nz = n != 0
    out[nz] = -1.0 / n[nz]
    return out
