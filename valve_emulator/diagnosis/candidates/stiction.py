r"""Candidate ``stiction``: the (S, J) valve of Choudhury, Thornhill & Shah (2005) between OP and MV.

Parameters: ``S`` (deadband + stickband, % travel, OP axis), ``J`` (slip jump, % travel, MV axis) and,
as a nuisance not counted by BIC, the valve's initial state ``start``
(:mod:`~valve_emulator.diagnosis.candidates.valve_start`, which also sets the burn-in).

Grids: ``S`` from one step to the robust OP span (a valve whose S exceeds the OP excursions never moves
and carries no information), ``J`` from 0 to ``1.6 S`` (overshoot included). Why three stages: with OP
noise the valve re-sticks at every small OP reversal, so a slip happens at the sample where OP first
crosses its threshold, and each half-cycle's slip sample flips at its own value of S. The cost is
therefore piecewise constant in S with cells a few hundredths of a percent wide, while within a cell it is
smooth in J (J scales the jump, not its timing). The coarse grid (step span/12) only picks the linear
dynamics; the scan is fine in S (span/160) and coarse in J (span/16) over the whole range; the refinement
searches ±2 scan steps of S at a quarter step and ±1.5 J steps at a sixth. The valve's model and rest
criterion are the nominal valve's.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from valve_emulator.diagnosis.candidates.base import ChainCandidate, ChainContext, TwinRole, register
from valve_emulator.diagnosis.candidates.valve_start import STARTS, valve_burn_in, valve_output

__all__ = ["Stiction", "stiction_kind"]

def stiction_kind(S: float, J: float) -> str:
    """``undershoot`` (J < S), ``no offset`` (J = S within 10 % of S) or ``overshoot`` (J > S)."""
    if abs(J - S) <= 0.1 * S:
        return "no offset"
    return "undershoot" if J < S else "overshoot"


def _coarse(span: float) -> float:
    return max(0.2, span / 12.0)


def scan_steps(span: float) -> tuple[float, float]:
    """(S step, J step) of the global scan over a travel span: S fine (span/160, at least 0.01), J coarse
    (span/16, at least 0.1). The interval profile of a stiction finding steps S by the same S step."""
    return max(0.01, span / 160.0), max(0.1, span / 16.0)


def _grid(S_values: np.ndarray, hJ: float) -> np.ndarray:
    rows = []
    for S in S_values:
        for J in np.arange(0, int(np.floor(1.6 * S / hJ + 1e-9)) + 1) * hJ:
            rows += [(S, J, start) for start in STARTS]
    return np.array(rows)


class Stiction(ChainCandidate):
    name: ClassVar[str] = "stiction"
    slot: ClassVar[str] = "valve"
    param_names: ClassVar[tuple[str, ...]] = ("S", "J", "start")
    n_params: ClassVar[int] = 2
    dims: ClassVar[dict[str, str]] = {"S": "op", "J": "op"}
    twin_role: ClassVar[TwinRole | None] = TwinRole.VALVE_BAND
    threshold_axes: ClassVar[tuple[int, ...]] = (0, 1)
    may_start_late: ClassVar[bool] = True
    output_in_range: ClassVar[bool] = True   # valve_output's MV

    def grid(self, ctx: ChainContext) -> np.ndarray:
        h = _coarse(ctx.op_span)
        return _grid(np.arange(1, max(2, int(np.floor(ctx.op_span / h)) + 1)) * h, h)

    def scan(self, ctx: ChainContext) -> np.ndarray:
        hS, hJ = scan_steps(ctx.op_span)
        return _grid(np.arange(1, max(2, int(np.floor(ctx.op_span / hS)) + 1)) * hS, hJ)

    def refine(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        hS, hJ = scan_steps(ctx.op_span)
        S0, J0, _ = best
        S = S0 + hS / 4.0 * np.arange(-8, 9)
        J = J0 + hJ / 6.0 * np.arange(-9, 10)
        SS, JJ = np.meshgrid(S[S > 0], J[J >= 0], indexing="ij")
        out = [np.column_stack([SS.ravel(), JJ.ravel(), np.full(SS.size, start)]) for start in STARTS]
        return np.vstack([best[None, :], *out])

    def profile_grid(self, ctx: ChainContext, best: np.ndarray) -> np.ndarray:
        """S within ±40 % of its estimate (33 values) × J from 0 to twice its estimate or 0.8 S (25 values),
        every start: the refinement grid (±2 scan steps) is far narrower than a short record's uncertainty."""
        S0, J0, _ = best
        S = S0 * np.linspace(0.6, 1.4, 33)
        J = np.linspace(0.0, max(2.0 * J0, 0.8 * S0), 25)
        SS, JJ = np.meshgrid(S, J, indexing="ij")
        rows = [np.column_stack([SS.ravel(), JJ.ravel(), np.full(SS.size, start)]) for start in STARTS]
        return np.vstack(rows)  # a regular grid: the interval is widened by half its step

    def burn_in(self, ctx: ChainContext) -> int:
        g = self.grid(ctx)
        return valve_burn_in(ctx.op, g[:, 0], g[:, 1], g[:, 2], ctx)

    def line(self, ctx: ChainContext, best: np.ndarray, axis: int) -> np.ndarray:
        h = scan_steps(ctx.op_span)[axis] / (80.0 if axis == 0 else 60.0)
        rows = np.repeat(best[None, :], 81, axis=0)
        rows[:, axis] = best[axis] + h * np.arange(-40, 41)
        return rows[rows[:, axis] >= (1e-9 if axis == 0 else 0.0)]

    def apply(self, x: np.ndarray, params: np.ndarray, ctx: ChainContext) -> np.ndarray:
        return valve_output(x, params[:, 0], params[:, 1], params[:, 2], ctx)

    def parameters(self, p: np.ndarray) -> dict:
        return {"S": round(float(p[0]), 3), "J": round(float(p[1]), 3)}

    def describe(self, p: np.ndarray, nominal: dict | None = None, units: str = " %",
                 edges: dict | None = None) -> str:
        return f"valve stiction: S ≈ {p[0]:.3g}{units}, J ≈ {p[1]:.3g}{units} ({stiction_kind(p[0], p[1])})"

    def identity(self) -> np.ndarray:
        return np.array([0.0, 0.0, STARTS[0]])


register(Stiction())
