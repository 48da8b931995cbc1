r"""The actuator: a first-order lag between the controller output and the valve's friction.

A pneumatic actuator and its positioner fill with air before the stem moves; to first order the travel demand
follows OP through ``1/(τ s + 1)``. The lag sits *before* the friction: the force builds up through the lag,
then the stem breaks free (stiction acts on the lagged demand). The diagnosis' ``actuator_lag`` candidate
(:mod:`valve_emulator.diagnosis.candidates.actuator_lag`) is this element in the same place of its chain, with
the same discretisation, so a twin that carries the lag found replays what the fit predicted:

OP is held over each sample, so the lag's state obeys the exact zero-order-hold recursion
``s_{k+1} = a s_k + (1 − a) OP_k`` with ``a = e^{−Δt/τ}``, and the valve reads the lag's *average* over the
sample, ``s_k + (OP_k − s_k) w`` with ``w = 1 − (τ/Δt)(1 − a)`` (the input-equivalent value for a plant much
slower than Δt; it tends to OP_k as τ → 0). ``τ = 0`` is no actuator: OP passes unchanged, bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike

__all__ = ["lag_coefficients", "actuator_output", "actuator_response"]


def lag_coefficients(tau: ArrayLike, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``(a, w)`` of the discretised lag for each time constant ``tau`` (s) at sample time ``dt`` (s); ``(0, 1)``
    where ``tau`` is 0 (no lag)."""
    tau = np.atleast_1d(np.asarray(tau, dtype=float))
    with np.errstate(divide="ignore", over="ignore"):
        a = np.where(tau > 0, np.exp(-dt / np.maximum(tau, 1e-300)), 0.0)
        w = np.where(tau > 0, 1.0 - (tau / dt) * (1.0 - a), 1.0)
    return a, w


@numba.njit(cache=True, inline="always")
def actuator_output(i, u, tau, a, w, state):  # pragma: no cover - compiled
    """The demand actuator ``i`` passes to the valve this sample for OP ``u``, advancing its state ``state[i]``
    (the lag's output at the start of the sample); ``u`` itself where ``tau[i]`` is 0."""
    if tau[i] <= 0.0:
        return u
    s = state[i]
    state[i] = a[i] * s + (1.0 - a[i]) * u
    return s + (u - s) * w[i]


@numba.njit(cache=True)
def _response(op, tau, a, w, state, out):  # pragma: no cover - compiled
    for k in range(op.shape[0]):
        out[k] = actuator_output(0, op[k], tau, a, w, state)


def actuator_response(op: ArrayLike, tau: float, dt: float) -> np.ndarray:
    """The demand a lag of ``tau`` s passes to the valve for the OP sequence ``op`` (%), started at rest at
    ``op[0]``: what the loop's compiled step does sample by sample, for a whole record."""
    op = np.ascontiguousarray(op, dtype=float)
    a, w = lag_coefficients(tau, dt)
    out = np.empty_like(op)
    if op.size:
        _response(op, np.array([float(tau)]), a, w, op[:1].copy(), out)
    return out
