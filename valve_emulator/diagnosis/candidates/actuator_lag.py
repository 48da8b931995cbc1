r"""Candidate ``actuator_lag``: a first-order lag τ between the controller output and the valve.

A pneumatic actuator and positioner fill with air before the stem moves; to first order the travel
demand follows OP through ``1/(τ s + 1)``. The lag acts before the valve's friction (the force builds up,
then the stem breaks free), so it sits in the ``actuator`` slot, ahead of stiction.

Discretisation (the coefficients are the device's actuator's, :func:`~valve_emulator.physics.actuator.
lag_coefficients`): OP is held over each sample, so the lag state obeys the exact ZOH recursion
``x_{k+1} = a x_k + (1 − a) OP_k`` with ``a = e^{−Δt/τ}``; the plant, itself discretised by ZOH, is fed the
*average* of the lag output over the sample, ``x_k + (OP_k − x_k)(1 − (τ/Δt)(1 − a))``, which is the
input-equivalent value for a plant much slower than Δt and reduces to OP_k as τ → 0.

Grid: τ log-spaced from Δt/4 to max(30 Δt, 2 τ_plant) (a lag much longer than the plant would be the plant
itself); :meth:`refine` searches a finer log grid around the best, never above the top. The top is a search
edge (:meth:`bounds`): a lag estimated there is reported as "τ ≥ …", not as a value. Below the bottom the
refinement may go on (a lag shorter than Δt/4 hardly differs from none, which is no edge of the physics).
"""

from __future__ import annotations

from typing import ClassVar

import numba
import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainCandidate, ChainContext, TwinRole, register, said
from valve_emulator.physics._arrays import kernel_array
from valve_emulator.physics.actuator import lag_coefficients

__all__ = ["ActuatorLag", "first_order_lag"]


@numba.njit(cache=True)
def _lag_kernel(x, a, w, out):  # pragma: no cover - compiled
    T, n = out.shape
    shared = x.shape[1] == 1
    for c in range(n):
        j = 0 if shared else c
        s = x[0, j]
        for k in range(T):
            u = x[k, j]
            out[k, c] = s + (u - s) * w[c]
            s = a[c] * s + (1.0 - a[c]) * u


def first_order_lag(x: np.ndarray, tau: np.ndarray, dt: float) -> np.ndarray:
    """Sample-averaged output (T, n) of ``1/(τ s + 1)`` for each τ, started at rest at ``x[0]``."""
    x = np.asarray(x, dtype=float)
    # writable and C-contiguous whatever the caller holds (a frozen recording is read-only): one compiled variant
    x2 = kernel_array(x[:, None] if x.ndim == 1 else x)
    a, w = lag_coefficients(tau, dt)
    out = np.empty((x2.shape[0], a.size))
    _lag_kernel(x2, a, w, out)
    return out


class ActuatorLag(ChainCandidate):
    name: ClassVar[str] = "actuator_lag"
    slot: ClassVar[str] = "actuator"
    param_names: ClassVar[tuple[str, ...]] = ("tau",)
    n_params: ClassVar[int] = 1
    joint_with_poles: ClassVar[bool] = True
    cause_rank: ClassVar[int | None] = 50
    twin_role: ClassVar[TwinRole | None] = TwinRole.ACTUATOR_LAG

    def grid(self, ctx: ChainContext) -> np.ndarray:
        return np.geomspace(*self._ends(ctx), 40)[:, None]

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        tau = np.unique(np.minimum(best[0] * np.exp(np.linspace(-0.4, 0.4, 17)), self._ends(ctx)[1]))
        return np.vstack([best[None, :], tau[:, None]])

    def bounds(self, ctx: ChainContext) -> dict[str, tuple[float | None, float | None]]:
        return {"tau": (None, self._ends(ctx)[1])}   # a lag below Δt/4 is no lag: not a search edge

    @staticmethod
    def _ends(ctx: ChainContext) -> tuple[float, float]:
        """The shortest and longest lag searched (s)."""
        return ctx.dt / 4.0, max(30.0 * ctx.dt, 2.0 * ctx.tau_plant)

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return first_order_lag(x, params[:, 0], ctx.dt)

    def parameters(self, p: np.ndarray) -> dict:
        return {"tau": round(float(p[0]), 3)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        tau = said("τ", "tau", p[0], ".1f", edges, " s")
        if edges and "tau" in edges:   # the top: longer than any positioner is slow
            tau += (", longer than the range searched: a valve whose travel barely follows OP within the record "
                    "(seized, a closed block valve or an open bypass) as likely as a slow actuator")
        if nominal is None:  # no model: nothing tells which of two lags in series is the actuator's
            return (f"an actuator lag or a second plant lag: {tau} (without a model the data cannot "
                    "separate the two)")
        return f"an actuator lag: {tau}"

    def identity(self) -> np.ndarray:
        return np.array([0.0])


register(ActuatorLag())
