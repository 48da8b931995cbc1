r"""Candidate ``deadband``: a pure deadband (backlash) of width S, the stiction model with J = 0.

With ``J = 0`` the (S, J) valve moves with ``MV = OP − d·S/2`` and never jumps, which is the classical
backlash (Choudhury, Thornhill & Shah 2005: "J = 0 pure deadband"). It is a separate candidate because it
has one parameter fewer than stiction, so BIC prefers it when no slip jump is visible. The initial state
``start`` is a nuisance on the grid, as for stiction (:mod:`~valve_emulator.diagnosis.candidates.valve_start`).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainCandidate, ChainContext, TwinRole, register
from valve_emulator.diagnosis.candidates.valve_start import STARTS, valve_burn_in, valve_output

__all__ = ["Deadband"]


def _step(span: float) -> float:
    return max(0.05, span / 40.0)


class Deadband(ChainCandidate):
    name: ClassVar[str] = "deadband"
    slot: ClassVar[str] = "valve"
    param_names: ClassVar[tuple[str, ...]] = ("S", "start")
    n_params: ClassVar[int] = 1
    dims: ClassVar[dict[str, str]] = {"S": "op"}
    may_start_late: ClassVar[bool] = True
    output_in_range: ClassVar[bool] = True   # valve_output's MV
    twin_role: ClassVar[TwinRole | None] = TwinRole.VALVE_BAND
    threshold_axes: ClassVar[tuple[int, ...]] = (0,)

    def grid(self, ctx: ChainContext) -> np.ndarray:
        h = _step(ctx.op_span)
        S = np.arange(1, max(2, int(np.floor(ctx.op_span / h)) + 1)) * h
        return np.column_stack([np.repeat(S, len(STARTS)), np.tile(STARTS, S.size)])

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        f = _step(ctx.op_span) / 10.0
        S = best[0] + f * np.arange(-12, 13)
        S = S[S > 0]
        rows = [np.column_stack([S, np.full(S.size, start)]) for start in STARTS]
        return np.vstack([best[None, :], *rows])

    def profile_grid(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        """S within ±40 % of its estimate (41 values), every start."""
        S = best[0] * np.linspace(0.6, 1.4, 41)
        rows = [np.column_stack([S, np.full(S.size, start)]) for start in STARTS]
        return np.vstack(rows)  # a regular grid: the interval is widened by half its step

    def burn_in(self, ctx: ChainContext) -> int:
        g = self.grid(ctx)
        return valve_burn_in(ctx.op, g[:, 0], np.zeros(g.shape[0]), g[:, 1], ctx)

    def line(self, ctx: ChainContext, best: np.ndarray, axis: int) -> np.ndarray:
        h = _step(ctx.op_span) / 200.0
        rows = np.repeat(best[None, :], 81, axis=0)
        rows[:, 0] = best[0] + h * np.arange(-40, 41)
        return rows[rows[:, 0] > 0]

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return valve_output(x, params[:, 0], np.zeros(params.shape[0]), params[:, 1], ctx)

    def parameters(self, p: np.ndarray) -> dict:
        return {"S": round(float(p[0]), 3)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"a valve deadband (backlash): S ≈ {p[0]:.3g}{units}"

    def identity(self) -> np.ndarray:
        return np.array([0.0, STARTS[0]])


register(Deadband())
