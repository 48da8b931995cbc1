r"""Candidate ``stiction``: the (S, J) valve of Choudhury, Thornhill & Shah (2005) between OP and MV.

Parameters: ``S`` (deadband + stickband, % travel, OP axis), ``J`` (slip jump, % travel, MV axis) and, as
a nuisance not counted by BIC, the valve's initial state. A recording starts mid-cycle and the valve's
state at the first sample is unknown (``/shared/notes`` §5); a model started stuck at OP(0) may never break
free when OP swings only a little more than S. We therefore start the valve *moving* at OP(0), in either
direction ``d = ±1`` (both are on the grid): it is put at rest at ``OP(0) − d(J + ε)`` having last moved
in direction ``d``, so the first sample already overcomes J and the valve moves with ``MV = OP − d(S−J)/2``.
A moving valve synchronises with the true one at the first OP reversal, so only a short burn-in is lost.

Grid: ``S`` from one step to the robust OP span (a valve whose S exceeds the OP excursions never moves
and carries no information), ``J`` from 0 to ``1.6 S`` (overshoot included), step ``span/20`` (at least
0.1 %); :meth:`refine` searches ±1.5 steps at a fifth of the step. The valve's model and rest criterion
are the nominal valve's.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import Candidate, ChainContext, register
from valve_emulator.physics.stiction import simulate_many

__all__ = ["Stiction", "valve_output", "stiction_kind"]

_EPS = 1e-6


def valve_output(x: np.ndarray, S: np.ndarray, J: np.ndarray, direction: np.ndarray,
                 ctx: ChainContext) -> np.ndarray:
    """MV (T, n) of valves started moving at ``x[0]`` in ``direction`` (see the module docstring)."""
    x = np.asarray(x, dtype=float)
    first = x[0] if x.ndim == 1 else x[0, :]
    S, J, d = (np.asarray(a, dtype=float) for a in (S, J, direction))
    op0 = np.clip(first - d * (J + _EPS), 0.0, 100.0)
    return simulate_many(x, S, J, model=ctx.valve_model, rest_samples=ctx.rest_samples, direction=d, op0=op0)


def stiction_kind(S: float, J: float) -> str:
    """``undershoot`` (J < S), ``no offset`` (J = S within 10 % of S) or ``overshoot`` (J > S)."""
    if abs(J - S) <= 0.1 * S:
        return "no offset"
    return "undershoot" if J < S else "overshoot"


def _step(span: float) -> float:
    return max(0.1, span / 20.0)


class Stiction(Candidate):
    name: ClassVar[str] = "stiction"
    slot: ClassVar[str] = "valve"
    param_names: ClassVar[tuple[str, ...]] = ("S", "J", "direction")
    n_params: ClassVar[int] = 2

    def grid(self, ctx: ChainContext) -> np.ndarray:
        h = _step(ctx.op_span)
        rows = []
        for S in np.arange(1, int(np.floor(ctx.op_span / h)) + 1) * h:
            for J in np.arange(0, int(np.floor(1.6 * S / h + 1e-9)) + 1) * h:
                rows += [(S, J, 1.0), (S, J, -1.0)]
        return np.array(rows) if rows else np.array([[h, 0.0, 1.0], [h, 0.0, -1.0]])

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        h = _step(ctx.op_span)
        f = h / 5.0
        S0, J0, d = best
        S = S0 + f * np.arange(-7, 8)
        J = J0 + f * np.arange(-7, 8)
        SS, JJ = np.meshgrid(S[S > 0], J[J >= 0], indexing="ij")
        out = np.column_stack([SS.ravel(), JJ.ravel(), np.full(SS.size, d)])
        return np.vstack([best[None, :], out])

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return valve_output(x, params[:, 0], params[:, 1], params[:, 2], ctx)

    def parameters(self, p: np.ndarray) -> dict:
        return {"S": round(float(p[0]), 3), "J": round(float(p[1]), 3)}

    def describe(self, p: np.ndarray, nominal: dict | None = None) -> str:
        return f"valve stiction: S ≈ {p[0]:.1f} %, J ≈ {p[1]:.1f} % ({stiction_kind(p[0], p[1])})"

    def identity(self) -> np.ndarray:
        return np.array([0.0, 0.0, 1.0])


register(Stiction())
